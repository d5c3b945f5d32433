"""The NDJSON codec (``fog_driver.ndjson``): one line buffer and one over-long policy for both sides."""

from __future__ import annotations

import random

import pytest

from fog_driver.client.wire import MAX_LINE_BYTES, LineReader
from fog_driver.ndjson import (
    OVERLONG,
    UNTERMINATED,
    Command,
    CommandError,
    LineBuffer,
    encode,
    parse_command,
)

LIMIT = 16


def expected(stream: bytes, limit: int) -> list:
    """The rule, written plainly: every complete line, or OVERLONG in its place; an unfinished last line over
    the limit is OVERLONG too (it is known to be too long before its newline comes)."""
    *complete, last = stream.split(b"\n")
    out: list = [OVERLONG if len(line) > limit else line for line in complete]
    if len(last) > limit:
        out.append(OVERLONG)
    return out


def fed(chunks, limit: int = LIMIT, **kw) -> list:
    buffer = LineBuffer(limit, **kw)
    return [item for chunk in chunks for item in buffer.feed(chunk)]


STREAM = (
    b"?WATCH;\n"
    + b"a" * (LIMIT - 1)
    + b"\n"
    + b"b" * LIMIT
    + b"\n"
    + b"c" * (LIMIT + 1)
    + b"\n\n"
    + b"d" * (LIMIT - 1)
    + b"\r\n"
    + b"e" * (3 * LIMIT)
    + b"\nok\n"
    + b"f" * (LIMIT + 5)
)


def test_the_stream_whole_gives_the_rule():
    assert fed([STREAM]) == expected(STREAM, LIMIT)
    assert fed([STREAM])[:4] == [b"?WATCH;", b"a" * (LIMIT - 1), b"b" * LIMIT, OVERLONG]


def test_bytes_fed_one_at_a_time_give_the_same_lines_and_events():
    assert fed([STREAM[i : i + 1] for i in range(len(STREAM))]) == expected(STREAM, LIMIT)


def test_every_split_point_gives_the_same_lines_and_events():
    for cut in range(len(STREAM) + 1):
        assert fed([STREAM[:cut], STREAM[cut:]]) == expected(STREAM, LIMIT), cut


def test_every_pair_of_split_points_gives_the_same_lines_and_events():
    stream = STREAM[: 4 * LIMIT]
    for a in range(len(stream) + 1):
        for b in range(a, len(stream) + 1):
            assert fed([stream[:a], stream[a:b], stream[b:]]) == expected(stream, LIMIT), (a, b)


@pytest.mark.parametrize("length", [LIMIT - 1, LIMIT, LIMIT + 1])
@pytest.mark.parametrize("chunk", [1, 3, LIMIT, LIMIT + 1, 1000])
def test_a_line_at_the_limit_passes_one_over_it_is_reported_once_and_dropped(length, chunk):
    stream = b"x" * length + b"\nnext\n"
    items = fed([stream[i : i + chunk] for i in range(0, len(stream), chunk)])
    if length <= LIMIT:
        assert items == [b"x" * length, b"next"]
    else:
        assert items == [OVERLONG, b"next"]


@pytest.mark.parametrize("length", [LIMIT - 1, LIMIT, LIMIT + 1])
def test_a_carriage_return_counts_against_the_limit(length):
    assert fed([b"y" * (length - 1) + b"\r\n"]) == ([OVERLONG] if length > LIMIT else [b"y" * (length - 1) + b"\r"])


@pytest.mark.parametrize("length", [LIMIT - 1, LIMIT, LIMIT + 1])
def test_an_unfinished_line_is_reported_as_soon_as_it_passes_the_limit(length):
    buffer = LineBuffer(LIMIT)
    assert list(buffer.feed(b"z" * length)) == ([OVERLONG] if length > LIMIT else [])
    assert list(buffer.feed(b"z" * 100)) == ([] if length > LIMIT else [OVERLONG])  # reported once only
    assert list(buffer.feed(b"\nafter\n")) == [b"after"]


def test_random_streams_in_random_chunks_follow_the_rule():
    rng = random.Random(29)
    for _ in range(300):
        stream = bytes(rng.choice(b"ab\n\r") for _ in range(rng.randrange(120)))
        chunks, at = [], 0
        while at < len(stream):
            step = rng.randrange(1, 12)
            chunks.append(stream[at : at + step])
            at += step
        assert fed(chunks, limit=5) == expected(stream, 5)


@pytest.mark.parametrize("extra", [-1, 0, 1])
def test_too_many_bytes_without_a_newline_are_reported(extra):
    cap = 64
    items = fed([b"w" * (cap + extra)], max_unterminated_bytes=cap)
    assert items == ([UNTERMINATED] if extra > 0 else [OVERLONG])  # checked before the line's own limit


def test_the_unterminated_count_includes_dropped_bytes_and_a_newline_resets_it():
    buffer = LineBuffer(LIMIT, max_unterminated_bytes=100)
    assert list(buffer.feed(b"v" * 60)) == [OVERLONG]
    assert buffer.unterminated_bytes == 60
    assert list(buffer.feed(b"v" * 41)) == [UNTERMINATED]
    buffer = LineBuffer(LIMIT, max_unterminated_bytes=100)
    assert list(buffer.feed(b"v" * 60 + b"\n" + b"u" * 10)) == [OVERLONG]
    assert buffer.unterminated_bytes == 10


def test_feed_works_as_it_is_consumed():
    """A consumer may stop after any line: nothing after it has been read (the hub closes a client so)."""
    buffer = LineBuffer(LIMIT)
    lines = buffer.feed(b"one\ntwo\nthree\n")
    assert next(lines) == b"one"
    lines.close()
    assert list(buffer.feed(b"four\n")) == [b"four"]


def test_the_clients_line_reader_keeps_its_limit_of_64_kib_plus_a_carriage_return():
    reader = LineReader()
    assert reader.feed(b"x" * MAX_LINE_BYTES + b"\r\n") == [b"x" * MAX_LINE_BYTES + b"\r"]
    assert reader.feed(b"x" * (MAX_LINE_BYTES + 1) + b"\r\n") == []
    assert reader.oversized == 1


@pytest.mark.parametrize(
    ("line", "parsed"),
    [
        (b"", None),
        (b"  \r", None),
        (b"?VERSION;", Command("VERSION", {}, False)),
        (b"?VERSION", Command("VERSION", {}, False)),
        (b"?WATCH={};\r", Command("WATCH", {}, True)),
        (b"?WATCH=;", Command("WATCH", {}, True)),
        (b'?WATCH={"rate_hz": 1} ;', Command("WATCH", {"rate_hz": 1}, True)),
        (b"WATCH;", CommandError("not a command: expected ?NAME; or ?NAME={json object};")),
        (b"?watch;", CommandError("not a command: expected ?NAME; or ?NAME={json object};")),
        (b"?WATCH=[1];", CommandError("the argument must be a JSON object", "WATCH")),
        (
            b"?ZERO={",
            CommandError(
                "invalid JSON: Expecting property name enclosed in double quotes: line 1 column 2 (char 1)", "ZERO"
            ),
        ),
        (b"?ZERO=" + b"[" * 5000, "invalid JSON"),
    ],
)
def test_parse_command(line, parsed):
    result = parse_command(line)
    if isinstance(parsed, str):
        assert isinstance(result, CommandError) and result.message.startswith(parsed)
    else:
        assert result == parsed


def test_encode_omits_absent_values_and_writes_one_compact_line():
    assert encode({"class": "X", "a": None, "b": float("nan"), "c": [1.5, None], "d": "null"}) == (
        b'{"class":"X","c":[1.5],"d":"null"}\n'
    )
