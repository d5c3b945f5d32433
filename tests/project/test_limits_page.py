"""docs/reference/limits.md against the code: every row's value is the bound the code applies.

Each row of the page's tables is looked up here by its first cell and its value cell must say what the
constant says, formatted as the page formats numbers; a row the test does not know, or a known row missing
from the page, fails too, so the page and the code cannot drift apart.
"""

from __future__ import annotations

import ast
import csv
import re
from pathlib import Path

import pytest

from fog_driver import dwells
from fog_driver.cli import argtypes
from fog_driver.client import protocol as client_protocol
from fog_driver.client import session, wire
from fog_driver.compensation import model, model_checks, reservoir, uncertainty
from fog_driver.daemon import config, limits
from fog_driver.files import yamlio
from fog_driver.lab import motion, plan, profiles
from fog_driver.sim import serve

PAGE = Path(__file__).resolve().parents[2] / "docs" / "reference" / "limits.md"


def _n(value: float) -> str:
    """A number as the page writes it: thousands separated by commas, no trailing .0."""
    return f"{int(value):,}" if float(value).is_integer() else f"{value:g}"


def _g(value: float) -> str:
    """A number in exponent form as the page writes it: 1e6, 1e-6."""
    return re.sub(r"e([+-])0*(\d)", lambda m: f"e{'-' if m[1] == '-' else ''}{m[2]}", f"{value:g}")


#: The page's rows: the first cell, and what the row must say (from the code's constants): the first item in its
#: value cell, the others anywhere in the row.
EXPECTED: dict[str, list[str]] = {
    "a YAML file: config, model, adaptation state, profile, sidecar": [f"{_n(yamlio.MAX_YAML_BYTES)} bytes"],
    "a reference stops CSV (`--reference`, `--table-log`)": [f"{_n(dwells.MAX_TABLE_LOG_BYTES)} bytes"],
    "a CSV field": [f"{_n(csv.field_size_limit())} characters"],
    "a token file (`--token-file`)": [f"{_n(wire.MAX_TOKEN_BYTES)} bytes"],
    "every number outside `provenance`": [f"at most {_g(model_checks.MAX_MODEL_NUMBER)}"],
    "candidate structures (`uncertainty.candidates`)": [_n(uncertainty.MAX_CANDIDATES)],
    "reservoir neurons (`n_neurons`)": [_n(reservoir.MAX_NEURONS)],
    "the model's block rate": [f"{model.MIN_MODEL_RATE_HZ:g} to {_n(model.MAX_MODEL_RATE_HZ)} Hz"],
    "YAML anchors and aliases": ["none"],
    "a command line": [f"{_n(limits.DEFAULT_MAX_LINE_BYTES)} bytes"],
    "bytes without a newline": [_n(limits.MAX_UNTERMINATED_BYTES)],
    "lines a second from one client": [_n(limits.MAX_COMMANDS_PER_S)],
    "refused excess lines": [_n(limits.MAX_EXCESS_COMMANDS)],
    "clients": [_n(limits.DEFAULT_MAX_CLIENTS)],
    "clients from one address (an IPv4 address or an IPv6 /64)": [_n(limits.DEFAULT_MAX_CLIENTS_PER_PEER)],
    "a client's oldest unsent line": [f"{_n(limits.DEFAULT_MAX_BACKLOG_S)} s"],
    "`?WATCH` `rate_hz`": [_n(limits.MAX_WATCH_RATE_HZ)],
    "`?TABLE` angle": [f"+-{_g(dwells.MAX_TABLE_ANGLE_DEG)} degrees"],
    "`?TABLE` dwell": [f"{_n(limits.MAX_TABLE_DWELL_S)} s"],
    "`?TABLE` from one client": [f"one each {_n(limits.TABLE_INTERVAL_S)} s"],
    "`?ADAPT` `reference_dph`": [f"+-{_g(limits.MAX_ADAPT_REFERENCE_DPH)} deg/h"],
    "`?BIAS` seconds": [f"{_n(limits.MIN_BIAS_S)} to {_n(limits.MAX_BIAS_S)}"],
    "log lines a second for each kind of client event": [_n(limits.DEFAULT_LOG_LINES_PER_S)],
    "the token's length": [
        f"at least {config.TOKEN_MIN_CHARS} characters",
        f"{config.TOKEN_REFUSED_BELOW_CHARS} to {config.TOKEN_MIN_CHARS - 1}",
        f"under {config.TOKEN_REFUSED_BELOW_CHARS}",
    ],
    "seconds to `?AUTH` after connecting": [_n(limits.DEFAULT_AUTH_DEADLINE_S)],
    "failed `?AUTH` on one connection": [_n(limits.MAX_AUTH_FAILURES)],
    "wrong tokens from one address before its backoff": [
        _n(limits.AUTH_FAILURES_BEFORE_BACKOFF),
        f"{_n(limits.DEFAULT_AUTH_BACKOFF_BASE_S)} s, doubling to {_n(limits.DEFAULT_AUTH_BACKOFF_MAX_S)} s",
    ],
    "addresses remembered": [_n(limits.MAX_THROTTLED_PEERS)],
    "connections": [_n(limits.WEB_MAX_CONNECTIONS)],
    "connections from one address": [_n(limits.WEB_MAX_CONNECTIONS_PER_PEER)],
    "the request line": [f"{_n(limits.WEB_MAX_LINE_BYTES)} bytes"],
    "a header": [f"{_n(limits.WEB_MAX_LINE_BYTES)} bytes"],
    "headers": [_n(limits.WEB_MAX_HEADERS)],
    "a request body": [f"{_n(limits.WEB_MAX_BODY_BYTES)} bytes"],
    "the request head": [f"within {_n(limits.WEB_REQUEST_HEAD_TIMEOUT_S)} s"],
    "the whole request": [f"within {_n(limits.WEB_REQUEST_TIMEOUT_S)} s"],
    "a session": [f"{_n(limits.WEB_SESSION_MAX_AGE_S / 3600)} h"],
    "sessions": [_n(limits.WEB_MAX_SESSIONS)],
    "a WebSocket message from the page": [f"{_n(limits.WEB_MAX_WS_MESSAGE_BYTES)} bytes"],
    "WebSocket messages a second from the page": [_n(limits.WEB_MAX_WS_MESSAGES_PER_S)],
    "`simulate --duration`, a fault, a profile": [f"{_n(profiles.MAX_PROFILE_S / 86400)} days"],
    "`simulate --speed` (with `--serve`)": [f"{_g(serve.MIN_SPEED)} to {_g(serve.MAX_SPEED)}"],
    "`--rate-hz` (`simulate`)": ["1 to 65,535 Hz"],
    "`--baud`": ["50 to 12,000,000"],
    "a profile's segments": [_n(profiles.MAX_SEGMENTS)],
    "a motion's moves": [_n(motion.MAX_MOVES)],
    "a table rate": [f"{_n(motion.MAX_TABLE_RATE_DPS)} deg/s"],
    "`plan`'s temperatures": [f"{plan.ABSOLUTE_ZERO_C:g} to {_n(plan.MAX_LIMIT_C)} degC"],
    "`plan`'s ramp rate": [f"{_n(plan.MAX_RATE_C_PER_MIN)} degC/min"],
    "`plan --minutes`": [f"({_n(plan.MAX_MINUTES)} min)"],
    "`ctl --timeout`": [f"at most {_n(argtypes.MAX_REPLY_TIMEOUT_S)} s"],
    "`watch --rate-hz`": [f"at most {_n(session.MAX_WATCH_RATE_HZ)}"],
    "`compensate --every`": [f"{_g(argtypes.MIN_PERIOD_S)} to {_g(argtypes.MAX_PERIOD_S)} s"],
}


def _rows() -> dict[str, tuple[str, str]]:
    """The page's table rows (first cell -> the value cell and the rest of the row), header and rule rows left out."""
    rows: dict[str, tuple[str, str]] = {}
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")] if line.startswith("| ") else []
        if len(cells) != 3 or cells[0] in ("limit", "---"):
            continue
        assert cells[0] not in rows, f"two rows named {cells[0]!r}"
        rows[cells[0]] = (cells[1], cells[2])
    return rows


def test_the_limits_page_names_every_bound_and_nothing_else() -> None:
    assert sorted(_rows()) == sorted(EXPECTED)


@pytest.mark.parametrize("label", sorted(EXPECTED))
def test_each_limit_on_the_page_is_the_one_the_code_applies(label: str) -> None:
    value, beyond = _rows()[label]
    first, *others = EXPECTED[label]
    assert first in value, f"{label!r}: the page says {value!r}, the code {first!r}"
    for expected in others:
        assert expected in f"{value} | {beyond}", (
            f"{label!r}: the page says {value!r} | {beyond!r}, the code {expected!r}"
        )


def test_the_arguments_bounds_the_page_quotes_are_the_parsers() -> None:
    """The option rows without a constant of their own: the argument types refuse just past them."""
    import argparse

    for parse, inside, outside in (
        (argtypes.rate_hz, ("1", "65535"), ("0", "65536")),
        (argtypes.baud, ("50", "12000000"), ("49", "12000001")),
    ):
        for text in inside:
            parse(text)
        for text in outside:
            with pytest.raises(argparse.ArgumentTypeError):
                parse(text)


def test_the_watch_rate_bound_is_one_on_both_sides_of_the_wire():
    """The client library refuses before asking what the daemon would refuse: the same bound."""
    assert session.MAX_WATCH_RATE_HZ == limits.MAX_WATCH_RATE_HZ


def test_the_bias_and_dwell_bounds_are_defined_once_in_the_client_library():
    """``?BIAS`` seconds and the ``?TABLE`` dwell: bound to a value in ``client/protocol.py`` alone (by the AST),
    so the daemon refuses exactly what the client library refuses before sending."""
    package = Path(__file__).resolve().parents[2] / "fog_driver"
    names = {"MAX_BIAS_S", "MAX_TABLE_DWELL_S"}
    bound: dict[str, list[str]] = {name: [] for name in names}
    for path in sorted(package.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets = (
                node.targets
                if isinstance(node, ast.Assign)
                else [node.target]
                if isinstance(node, ast.AnnAssign)
                else []
            )
            for target in targets:
                if isinstance(target, ast.Name) and target.id in names:
                    bound[target.id].append(path.relative_to(package).as_posix())
    assert bound == {name: ["client/protocol.py"] for name in names}
    assert (limits.MAX_BIAS_S, limits.MAX_TABLE_DWELL_S) == (
        client_protocol.MAX_BIAS_S,
        client_protocol.MAX_TABLE_DWELL_S,
    )
