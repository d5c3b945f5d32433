"""The NDJSON connection state machine (``fog_driver.daemon.connection``), driven with bytes and a clock: no socket."""

from __future__ import annotations

import pytest

from fog_driver.daemon.connection import (
    AuthGate,
    Authorized,
    Close,
    Connection,
    Control,
    Log,
    Send,
    SendDevice,
    SendVersion,
    WatchChanged,
    control_error,
    control_reply,
)
from fog_driver.daemon.guards import AuthThrottle
from fog_driver.daemon.limits import (
    AUTH_FAILURES_BEFORE_BACKOFF,
    MAX_AUTH_FAILURES,
    MAX_COMMANDS_PER_S,
    MAX_EXCESS_COMMANDS,
    MAX_UNTERMINATED_BYTES,
)


class Clock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def connection(
    token: str | None = None, *, max_line_bytes: int = 64, gate: AuthGate | None = None, peer: str = "10.0.0.1"
):
    clock = Clock()
    gate = gate or AuthGate(token, AuthThrottle(1.0, 300.0))
    return Connection(peer, gate, max_line_bytes=max_line_bytes, clock=clock), clock


def run(conn: Connection, data: bytes) -> list:
    return list(conn.receive(data))


def sent(actions) -> list[dict]:
    return [a.obj for a in actions if isinstance(a, Send)]


def test_a_new_connection_is_greeted_with_version_and_device_or_version_alone_behind_a_token():
    assert connection()[0].greeting() == [SendVersion(), SendDevice()]
    # behind a token: VERSION without the instrument's identity (its serial), until ?AUTH
    conn, _ = connection("s3cret")
    assert conn.greeting() == [SendVersion(identity=False)]
    assert run(conn, b"?VERSION;\n") == [SendVersion(identity=False)]
    run(conn, b'?AUTH={"token": "s3cret"};\n')
    assert run(conn, b"?VERSION;\n") == [SendVersion(identity=True)]


def test_behind_a_token_angles_need_auth_unless_the_stream_is_open():
    """A token protected the commands only: an unauthorized client got every ANGLE it watched."""
    conn, _ = connection("s3cret")
    assert sent(run(conn, b'?WATCH={"enable": true};\n')) == [
        {"class": "ERROR", "message": "unauthorized", "command": "WATCH"}
    ]
    assert not conn.watch and not conn.reads_angles
    assert sent(run(conn, b"?WATCH;\n")) == [{"class": "WATCH", "enable": False, "rate_hz": None}]  # asking is free
    run(conn, b'?AUTH={"token": "s3cret"};\n')
    run(conn, b'?WATCH={"enable": true};\n')
    assert conn.reads_angles
    opened = AuthGate("s3cret", AuthThrottle(1.0, 300.0), open_stream=True)
    reader, _ = connection(gate=opened)
    assert not reader.reads_angles  # not watching
    run(reader, b'?WATCH={"enable": true};\n')
    assert reader.reads_angles and not reader.authorized
    assert reader.auth_deadline_passed(10.0) == []  # a reader of the open stream needs no token
    assert sent(run(reader, b"?ZERO;\n")) == [{"class": "ERROR", "message": "unauthorized", "command": "ZERO"}]
    run(reader, b'?WATCH={"enable": false};\n')
    assert reader.auth_deadline_passed(10.0)[-1] == Close()  # no longer reading: the deadline applies
    assert connection()[0].reads_angles is False and connection()[0].authorized  # no token: watch to read


def test_watch_sets_the_policy_and_reports_it():
    conn, _ = connection()
    assert run(conn, b"?WATCH;\n") == [Send({"class": "WATCH", "enable": False, "rate_hz": None})]
    assert run(conn, b'?WATCH={"rate_hz": 2};\n') == [
        WatchChanged(True),
        Send({"class": "WATCH", "enable": True, "rate_hz": 2}),
    ]
    assert conn.watch and conn.rate_hz == 2
    assert run(conn, b'?WATCH={"enable": false}\r\n') == [
        WatchChanged(False),
        Send({"class": "WATCH", "enable": False, "rate_hz": None}),
    ]
    assert sent(run(conn, b'?WATCH={"rate_hz": 0};\n'))[0]["message"].startswith("rate_hz must be a number > 0")
    assert sent(run(conn, b'?WATCH={"enable": 1};\n'))[0]["message"] == "enable must be true or false"


def test_the_watch_decimation_keeps_the_first_sample_of_each_period_of_device_time():
    conn, _ = connection()
    run(conn, b'?WATCH={"rate_hz": 2};\n')
    items = [(t / 10, f"{t}".encode()) for t in range(12)]
    assert conn.keep_angles(items[:7]) == [b"0", b"5"]
    assert conn.keep_angles(items[7:]) == [b"10"]  # the period carries over from batch to batch
    run(conn, b"?WATCH={};\n")
    assert conn.keep_angles(items[:3]) == [b"0", b"1", b"2"]


def test_other_commands_go_to_the_service_and_errors_are_answered_here():
    conn, _ = connection()
    assert run(conn, b'?ZERO;\n?MARK={"label": "x"};\n') == [Control("ZERO", {}), Control("MARK", {"label": "x"})]
    assert run(conn, b"?VERSION;\n") == [SendVersion()]
    assert sent(run(conn, b"hello\n")) == [
        {"class": "ERROR", "message": "not a command: expected ?NAME; or ?NAME={json object};", "command": None}
    ]
    assert sent(run(conn, b"?ZERO=[1];\n")) == [
        {"class": "ERROR", "message": "the argument must be a JSON object", "command": "ZERO"}
    ]
    assert run(conn, b"\n   \n") == []


@pytest.mark.parametrize("length", [63, 64, 65])
def test_an_over_long_line_is_answered_with_error_and_the_next_one_is_read(length):
    conn, _ = connection(max_line_bytes=64)
    line = b"?MARK=" + b"x" * (length - 6)
    actions = run(conn, line[:30]) + run(conn, line[30:] + b"\n?ZERO;\n")
    if length <= 64:
        assert sent(actions)[0]["message"].startswith("invalid JSON")
    else:
        assert sent(actions) == [{"class": "ERROR", "message": "line longer than 64 bytes: discarded", "command": None}]
    assert actions[-1] == Control("ZERO", {})
    assert not conn.closing


def test_too_many_bytes_without_a_newline_close_the_connection():
    conn, _ = connection()
    actions = run(conn, b"x" * 100) + run(conn, b"x" * MAX_UNTERMINATED_BYTES)
    assert actions[-1] == Close() and conn.closing
    assert sent(actions)[-1]["message"] == f"more than {MAX_UNTERMINATED_BYTES} bytes without a newline: closing"
    assert run(conn, b"?ZERO;\n") == []


def test_the_rate_limit_counts_every_line_refuses_the_excess_and_closes_at_the_last():
    conn, clock = connection()
    actions = run(conn, b"\n" * MAX_COMMANDS_PER_S + b"?ZERO;\n")
    assert sent(actions) == [
        {"class": "ERROR", "message": f"more than {MAX_COMMANDS_PER_S} commands per second: refused", "command": None}
    ]
    clock.now_s += 1.0
    assert run(conn, b"?ZERO;\n") == [Control("ZERO", {})]  # a new second
    actions = run(conn, b"\n" * (MAX_COMMANDS_PER_S + MAX_EXCESS_COMMANDS + 10))
    assert actions[-1] == Close()
    # one refusal a second, whatever the flood (before: one ERROR line written for every line received),
    # then the closing line; nothing after the close
    assert [m["message"] for m in sent(actions)] == [
        f"more than {MAX_COMMANDS_PER_S} commands per second: refused",
        f"{MAX_EXCESS_COMMANDS} commands over the rate limit: closing",
    ]


def test_an_excess_line_is_answered_once_a_second():
    conn, clock = connection()
    run(conn, b"\n" * MAX_COMMANDS_PER_S)
    assert len(sent(run(conn, b"\n" * 50))) == 1  # the first excess line told, the others dropped
    assert run(conn, b"?ZERO;\n") == []  # refused without an answer: still the same second
    clock.now_s += 1.0
    assert run(conn, b"?ZERO;\n") == [Control("ZERO", {})]


def test_behind_a_token_commands_are_refused_until_auth_and_then_device_follows():
    conn, _ = connection("s3cret")
    assert sent(run(conn, b"?ZERO;\n")) == [{"class": "ERROR", "message": "unauthorized", "command": "ZERO"}]
    actions = run(conn, b'?AUTH={"token": "s3cret"};\n')
    assert actions == [Authorized(), Send({"class": "AUTH", "authorized": True}), SendDevice()]
    assert run(conn, b'?AUTH={"token": "s3cret"};\n') == [Authorized(), Send({"class": "AUTH", "authorized": True})]
    assert run(conn, b"?ZERO;\n") == [Control("ZERO", {})]


def test_wrong_tokens_are_logged_refused_and_close_the_connection_at_the_last_attempt():
    gate = AuthGate("s3cret", AuthThrottle(1.0, 300.0))
    conn, clock = connection(gate=gate)
    messages = []
    for attempt in range(MAX_AUTH_FAILURES):
        actions = run(conn, b'?AUTH={"token": "nope"};\n')
        messages += [a.obj["message"] for a in actions if isinstance(a, Send)]
        if attempt < AUTH_FAILURES_BEFORE_BACKOFF:
            assert isinstance(actions[0], Log) and actions[0].event == "auth_failed"
            assert actions[0].fields["failures"] == attempt + 1
        clock.now_s += 0.1
    assert messages[:AUTH_FAILURES_BEFORE_BACKOFF] == ["bad token"] * AUTH_FAILURES_BEFORE_BACKOFF
    assert messages[-1].endswith(": closing") and conn.closing
    # the backoff is the peer's, across connections: a wrong guess from a new one from the same address waits too
    other, _ = connection(gate=gate)
    other.clock = clock
    refused = sent(run(other, b'?AUTH={"token": "guess"};\n'))
    assert refused[0]["message"].startswith("too many failed attempts, retry in")


def test_a_guesser_in_its_backoff_gets_the_same_retry_answer_for_the_right_token_and_a_wrong_one():
    """The backoff compared every token: a right one was accepted while a wrong one got "retry", so each guess
    had its verdict at any rate.  Now no token from a blocked address is compared; after the block the right
    one works, and another address is never blocked."""
    gate = AuthGate("s3cret", AuthThrottle(1.0, 300.0))
    guesser, clock = connection(gate=gate)
    for _ in range(AUTH_FAILURES_BEFORE_BACKOFF + 1):  # the backoff starts: the address is blocked for 1 s
        assert sent(run(guesser, b'?AUTH={"token": "nope"};\n'))[0]["message"] == "bad token"
    assert gate.throttle.blocked_for_s("10.0.0.1", clock.now_s) == 1.0
    answers = []
    for token in (b"s3cret", b"nope"):
        other, _ = connection(gate=gate)  # the same address, a new connection
        other.clock = clock
        answers.append(sent(run(other, b'?AUTH={"token": "' + token + b'"};\n')))
        assert not other.authorized
    assert (
        answers[0]
        == answers[1]
        == [{"class": "ERROR", "message": "too many failed attempts, retry in 1 s", "command": "AUTH"}]
    )
    elsewhere, _ = connection(gate=gate, peer="10.0.0.2")
    elsewhere.clock = clock
    assert sent(run(elsewhere, b'?AUTH={"token": "s3cret"};\n')) == [{"class": "AUTH", "authorized": True}]
    clock.now_s += 1.0  # the block is over: the right token works
    operator, _ = connection(gate=gate)
    operator.clock = clock
    assert sent(run(operator, b'?AUTH={"token": "s3cret"};\n')) == [{"class": "AUTH", "authorized": True}]


def test_the_auth_deadline_and_a_token_change_close_the_connection():
    conn, _ = connection("s3cret")
    actions = conn.auth_deadline_passed(10.0)
    assert actions[1:] == [
        Send({"class": "ERROR", "message": "not authorized within 10 s: closing", "command": "AUTH"}),
        Close(),
    ]
    assert conn.auth_deadline_passed(10.0) == []
    conn, _ = connection()
    assert conn.token_changed() == [
        Send({"class": "ERROR", "message": "the client token changed: connect again", "command": "AUTH"}),
        Close(),
    ]


def test_the_end_of_input_closes_once():
    conn, _ = connection()
    assert conn.end_of_input() == [Close()]
    assert conn.end_of_input() == []


def test_a_service_answer_becomes_one_line():
    assert control_reply("ZERO", {"zeroed": True}) == {"class": "ZERO", "zeroed": True}
    assert control_reply("ZERO", {"class": "ERROR", "message": "m"}) == {
        "class": "ERROR",
        "message": "m",
        "command": "ZERO",
    }
    assert control_reply("NOPE", None) == {"class": "ERROR", "message": "unknown command ?NOPE", "command": "NOPE"}
    assert control_reply("ZERO", 3)["message"] == "internal: bad reply"
    assert control_error("ZERO", ValueError()) == {"class": "ERROR", "message": "ValueError", "command": "ZERO"}


def test_one_table_angle_per_two_seconds_per_client():
    conn, clock = connection()
    line = b'?TABLE={"angle_deg": 36, "dwell_s": 60};\n'
    assert run(conn, line) == [Control("TABLE", {"angle_deg": 36, "dwell_s": 60})]
    clock.now_s += 1.9
    assert sent(run(conn, line)) == [
        {"class": "ERROR", "message": "at most one ?TABLE per 2 s: refused", "command": "TABLE"}
    ]
    assert run(conn, b"?ZERO;\n") == [Control("ZERO", {})]  # other commands are not held back
    clock.now_s += 0.1
    assert run(conn, line) == [Control("TABLE", {"angle_deg": 36, "dwell_s": 60})]  # 2 s after the one taken
    other, _ = connection()  # another client has its own allowance
    assert run(other, line) == [Control("TABLE", {"angle_deg": 36, "dwell_s": 60})]
