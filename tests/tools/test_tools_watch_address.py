"""``fog-driver watch``'s daemon addresses (``fog_driver.tools.watch``): ``HOST:PORT`` and ``[V6]:PORT`` read
and written back, and what is refused."""

from __future__ import annotations

import pytest

from fog_driver.errors import UsageError
from fog_driver.tools.watch import (
    format_address,
    parse_address,
)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (None, ("127.0.0.1", 2948)),
        ("", ("127.0.0.1", 2948)),
        ("gyro-pc", ("gyro-pc", 2948)),
        ("gyro-pc:3000", ("gyro-pc", 3000)),
        (":3000", ("127.0.0.1", 3000)),
        ("3000", ("127.0.0.1", 3000)),
        ("[::1]:3000", ("::1", 3000)),
        ("[::1]", ("::1", 2948)),
        ("::1", ("::1", 2948)),
    ],
)
def test_parse_address(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize(
    ("host", "text"),
    [
        ("127.0.0.1", "127.0.0.1:2948"),
        ("gyro-pc", "gyro-pc:2948"),
        ("::1", "[::1]:2948"),
        ("fe80::1%eth0", "[fe80::1%eth0]:2948"),
    ],
)
def test_format_address_is_read_back_by_parse_address(host, text):
    assert format_address(host, 2948) == text
    assert parse_address(text) == (host, 2948)


@pytest.mark.parametrize("text", ["host:port", "host:0", "host:70000", "[::1", "[::1]x"])
def test_parse_address_rejects(text):
    with pytest.raises(UsageError):
        parse_address(text)
