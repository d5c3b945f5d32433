"""The ``web`` fixture (a factory of started ``WebView`` listeners on a free port, stopped after the test), for
test_daemon_web.py and test_web_access.py; conftest.py registers it as a plugin, so no test module imports a
fixture."""

from __future__ import annotations

import pytest

from fog_driver.daemon.web.server import WebView


@pytest.fixture
def web():
    started: list[WebView] = []

    def make(host: str = "127.0.0.1", **kw) -> WebView:
        view = WebView(host, 0, **kw)
        view.start()
        started.append(view)
        return view

    yield make
    for view in started:
        view.stop()
