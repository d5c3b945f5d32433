"""Shared test settings."""

import os

from hypothesis import settings

# The machines are shared and noisy: no per-example deadlines (speed is measured by benchmarks/,
# never asserted in tests).  Examples stay random locally; CI=true derandomizes them so a CI run
# is reproducible.
settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")
