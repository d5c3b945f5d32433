"""Shared test settings."""

import os

import pytest
import structlog
from hypothesis import settings

# The machines are shared and noisy: no per-example deadlines (speed is measured by benchmarks/,
# never asserted in tests).  Examples stay random locally; CI=true derandomizes them so a CI run
# is reproducible.
settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")

# Fixtures shared by several test modules live in plugin modules here (a test module imports no fixture).
pytest_plugins = ["hub_fixtures"]


@pytest.fixture(autouse=True)
def _structlog_defaults():
    """A command's ``configure_logging`` must not outlive its test (its stderr may be a closed capture)."""
    yield
    structlog.reset_defaults()
