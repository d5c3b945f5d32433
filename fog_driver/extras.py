"""Optional extras (``pyproject.toml``'s ``report``, ``svr``, ``web`` and ``lab``): checked before a command does any
work, with the README's own install command in the message."""

from __future__ import annotations

import importlib

from .errors import UsageError

#: extra -> the modules it provides (import name, the package's name in messages).
EXTRAS = {
    "report": (("allantools", "allantools"), ("matplotlib", "matplotlib")),
    "svr": (("sklearn.svm", "scikit-learn"),),
    "web": (("aiohttp", "aiohttp"), ("plotly", "plotly"), ("prometheus_client", "prometheus-client")),
    "lab": (("pymodbus", "pymodbus"),),
}


def install_hint(extra: str) -> str:
    """How to install ``extra``, as the README does it (an editable install in the project's venv)."""
    return f"in the project's virtual environment: pip install -e '.[{extra}]'"


def missing_message(extra: str, purpose: str, missing: list[str]) -> str:
    return f"{purpose} needs {' and '.join(missing)} (the '{extra}' extra); {install_hint(extra)}"


def require_extra(extra: str, purpose: str) -> None:
    """A one-line ``UsageError`` unless every module of ``extra`` imports (call it before any long work)."""
    missing = []
    for module, name in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError:
            missing.append(name)
    if missing:
        raise UsageError(missing_message(extra, purpose, missing))
