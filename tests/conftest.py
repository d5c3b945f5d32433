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
pytest_plugins = ["hub_fixtures", "web_fixtures"]


@pytest.fixture(autouse=True)
def _structlog_defaults():
    """A command's ``configure_logging`` must not outlive its test (its stderr may be a closed capture)."""
    yield
    structlog.reset_defaults()


def pytest_collection_modifyitems(config, items):
    """In CI the soak runs for 600 s beside the suite (``.ci/run`` sets ``FOG_SOAK_BESIDE``): the suite's own
    60-s run of the same test is then skipped, saying so (it would only repeat the first tenth of it)."""
    if not os.environ.get("FOG_SOAK_BESIDE"):
        return
    beside = pytest.mark.skip(reason="the same soak runs for 600 s beside this run (FOG_SOAK_BESIDE, CI)")
    for item in items:
        if item.get_closest_marker("soak"):
            item.add_marker(beside)
