"""The daemon's own error (a leaf: every daemon module may raise it)."""

from __future__ import annotations

from ..errors import FogDriverError

__all__ = ["ConfigError"]


class ConfigError(FogDriverError):
    """A bad configuration or model: exit 78 (EX_CONFIG), so systemd does not restart in a loop."""

    exit_status = 78
