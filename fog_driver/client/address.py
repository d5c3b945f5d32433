"""The daemon's address as text: ``HOST:PORT`` read (``parse_host_port``) and written (``format_address``).

Shared by the client library and the daemon's configuration (standard library only).
"""

from __future__ import annotations

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "format_address", "parse_host_port"]

#: Where ``fog-driver run`` listens by default, and where clients look for it.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 2948


def parse_host_port(
    text: str | None, *, default_host: str = DEFAULT_HOST, default_port: int = DEFAULT_PORT, allow_zero: bool = True
) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT``, ``PORT``, ``[IPV6]:PORT`` or a bare IPv6 address -> (host, port).

    ``ValueError`` naming the problem when malformed; port 0 (any free port) only with ``allow_zero``.
    """
    if text is None or not text.strip():
        return default_host, default_port
    text = text.strip()
    host, port_text = text, ""
    if text.startswith("["):  # [::1] or [::1]:2948
        end = text.find("]")
        if end < 0:
            raise ValueError(f"{text!r}: not HOST:PORT (an IPv6 address needs a closing ']')")
        host, rest = text[1:end], text[end + 1 :]
        if rest and not rest.startswith(":"):
            raise ValueError(f"{text!r}: not HOST:PORT")
        port_text = rest[1:]
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    elif text.count(":") > 1:  # a bare IPv6 address
        host = text
    elif text.isdigit():
        host, port_text = "", text
    host = host or default_host
    if not port_text:
        return host, default_port
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"{text!r}: port {port_text!r} is not a number") from None
    if not (0 if allow_zero else 1) <= port <= 65535:
        raise ValueError(f"{text!r}: port {port} is out of range")
    return host, port


def format_address(host: str, port: int) -> str:
    """``HOST:PORT``, with an IPv6 address in brackets (``[::1]:2948``): what ``parse_host_port`` reads back."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
