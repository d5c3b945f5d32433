"""Tests of fog_driver.transport.setup (device setup commands) and PortReader's on_open hook.

The device is ``fog_driver.sim.kvh_device.FakeKvhDevice`` on a pty.  No test sleeps to synchronise:
``run_setup`` itself waits for each reply, the reader thread (``readerthread.Reader``) hands its events
and chunks over through one ordered queue, the fake device reports each command it handled on a queue, and a bare pty's
master is read with select (``PtyPair.read_available``).  Timeouts are failure guards only.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from readerthread import Reader

from fog_driver.formats.kvh import KvhDecoder
from fog_driver.sim.kvh_device import FakeKvhDevice
from fog_driver.transport import PortError, PortEvent, PortReader, PtyPair, open_port
from fog_driver.transport.setup import (
    DeviceSetup,
    DeviceSetupError,
    InvalidSetupCommand,
    SetupResult,
    make_on_open,
    run_setup,
)

GUARD_S = 10.0  #: failure guard for waits on other threads; never reached when things work


@pytest.fixture
def device() -> Iterator[tuple[PtyPair, FakeKvhDevice]]:
    with PtyPair() as pair, FakeKvhDevice(pair, frames_before_config=3, frames_after_config=2) as dev:
        yield pair, dev


def frames_in(data: bytes) -> int:
    """How many CRC-valid KVH frames ``data`` holds (the replies in between are skipped by the decoder)."""
    decoder = KvhDecoder()
    return len(decoder.feed(data) + decoder.close())


# ---------------------------------------------------------------------------------------------
# validation at configuration load


@pytest.mark.parametrize(
    ("command", "fragment"),
    [
        ("TEMPUNITS,C_100", "must start with '=' (set) or '?' (query)"),
        ("=TEMPUNITS,C\n", "a line break"),
        ("=DR,100\r=CONFIG,0", "a line break"),
        ("=TEMP UNITS,C", "a space"),
        ("=TEMPUNITS,\u00b0C", "character '\u00b0'"),
        ("=TEMPUNITS,\x00", "character '\\x00'"),
        ("=" + "A" * 200, "longer than 128 characters"),
        ("", "empty"),
        ("=", "no keyword"),
        ("=CONFIG,0", "config mode is entered and left by the setup itself"),
        ("=config,1", "config mode is entered and left by the setup itself"),
        ("=BAUD,9600", "baud rate"),
        (42, "not a string"),
    ],
)
def test_invalid_commands_are_refused_with_one_line(command: object, fragment: str) -> None:
    with pytest.raises(InvalidSetupCommand) as info:
        DeviceSetup(("=TEMPUNITS,C", command))  # type: ignore[arg-type]
    message = str(info.value)
    assert fragment in message
    assert "\n" not in message and "\r" not in message
    assert len(message) < 200


def test_setup_from_mapping_validates_keys_types_and_numbers() -> None:
    setup = DeviceSetup.from_mapping({"commands": ["=TEMPUNITS,C_100", "?DR"], "settle_s": 2.5})
    assert setup.commands == ("=TEMPUNITS,C_100", "?DR")
    assert (setup.settle_s, setup.reply_timeout_s, setup.terminator) == (2.5, 1.0, b"\r\n")
    assert DeviceSetup.from_mapping(None).commands == ()
    with pytest.raises(InvalidSetupCommand, match="expected a list, got str"):
        DeviceSetup.from_mapping({"commands": "=DR,100"})
    with pytest.raises(InvalidSetupCommand, match="unknown key"):
        DeviceSetup.from_mapping({"command": ["=DR,100"]})
    with pytest.raises(InvalidSetupCommand, match="reply_timeout_s"):
        DeviceSetup(("=DR,100",), reply_timeout_s=0)
    with pytest.raises(InvalidSetupCommand, match="settle_s"):
        DeviceSetup(("=DR,100",), settle_s=-1)
    with pytest.raises(InvalidSetupCommand, match="reply_timeout_s True"):
        DeviceSetup.from_mapping({"commands": ["=DR,100"], "reply_timeout_s": True})
    with pytest.raises(InvalidSetupCommand, match="terminator"):
        DeviceSetup(("=DR,100",), terminator=b";")


def test_wire_wraps_commands_in_config_mode_with_crlf() -> None:
    assert DeviceSetup(()).wire() == []
    assert DeviceSetup(("=tempunits,c_100", "?DR")).wire() == [
        ("=CONFIG,1", b"=CONFIG,1\r\n", "CONFIG,1"),
        ("=tempunits,c_100", b"=tempunits,c_100\r\n", "TEMPUNITS,C_100"),
        ("?DR", b"?DR\r\n", "DR"),
        ("=CONFIG,0", b"=CONFIG,0\r\n", "CONFIG,0"),
    ]


# ---------------------------------------------------------------------------------------------
# run_setup against the fake device


def test_commands_reach_the_device_in_order_inside_config_mode(device: tuple[PtyPair, FakeKvhDevice]) -> None:
    pair, dev = device
    setup = DeviceSetup(("=TEMPUNITS,C_100", "=rotfmt,rate", "=DR,500", "?ROTUNITS"), settle_s=1.5)
    port = open_port(pair.slave_path, timeout_s=0.05)
    try:
        t0 = time.monotonic()
        result = run_setup(port, setup)
        t1 = time.monotonic()
    finally:
        port.close()
    assert bytes(dev.received) == (
        b"=CONFIG,1\r\n=TEMPUNITS,C_100\r\n=rotfmt,rate\r\n=DR,500\r\n?ROTUNITS\r\n=CONFIG,0\r\n"
    )
    assert result.sent == tuple(wire for _, wire, _ in setup.wire())
    assert result.replies == ("CONFIG,1", "TEMPUNITS,C_100", "ROTFMT,RATE", "DR,500", "ROTUNITS,RAD", "CONFIG,0")
    assert dev.settings == {"TEMPUNITS": "C_100", "ROTFMT": "RATE", "ROTUNITS": "RAD", "DR": "500"}
    assert (dev.config_entries, dev.config_mode) == (1, False)  # entered once and left
    assert result.settle_s == 1.5
    assert t0 <= result.finished_monotonic <= t1
    assert result.settle_until_monotonic == pytest.approx(result.finished_monotonic + 1.5)


def test_bytes_read_during_setup_are_returned_and_passed_on(device: tuple[PtyPair, FakeKvhDevice]) -> None:
    pair, dev = device
    seen: list[bytes] = []
    port = open_port(pair.slave_path, timeout_s=0.05)
    try:
        result = run_setup(port, DeviceSetup(("=TEMPUNITS,C_100",)), on_bytes=seen.append)
        rest = bytearray()
        while len(result.raw) + len(rest) < len(dev.sent):  # the frames after CONFIG,0 not read yet
            chunk = port.read(64)
            assert chunk, "the frames sent after CONFIG,0 never arrived"
            rest += chunk
    finally:
        port.close()
    assert b"".join(seen) == result.raw
    assert result.raw + bytes(rest) == bytes(dev.sent)  # nothing lost, nothing added, in order
    reply_end = result.raw.index(b"CONFIG,0\r\n") + len(b"CONFIG,0\r\n")
    assert frames_in(result.raw[:reply_end]) == 3  # the frames in flight when config mode was asked for
    assert frames_in(result.raw + bytes(rest)) == 5  # and the two after it
    assert result.raw[:4] == b"\xfe\x81\xff\x55"


def test_streaming_stops_in_config_mode_and_resumes_with_the_new_settings() -> None:
    with PtyPair() as pair, FakeKvhDevice(pair, rate_hz=500.0, frames_before_config=0) as dev:
        port = open_port(pair.slave_path, timeout_s=0.05)
        try:
            first = port.read(36)  # the stream is running (a read waits for the bytes, no sleep)
            result = run_setup(port, DeviceSetup(("=TEMPUNITS,C_100",)))
            after = bytearray()
            while frames_in(bytes(after)) < 3:  # three streamed frames after the setup
                chunk = port.read(256)
                assert chunk, "the stream did not resume after CONFIG,0"
                after += chunk
        finally:
            port.close()
            dev.close()
    raw = first + result.raw
    start = raw.index(b"CONFIG,1\r\n") + len(b"CONFIG,1\r\n")
    assert raw[start : raw.index(b"CONFIG,0\r\n")] == b"TEMPUNITS,C_100\r\n"  # no frame in config mode
    decoder = KvhDecoder()
    before = decoder.feed(raw[: raw.index(b"CONFIG,1")])
    assert before and {s.temps_c["sensor"] for s in before} == {25.0}  # degC words before the change
    decoder = KvhDecoder()
    resumed = decoder.feed(raw[raw.index(b"CONFIG,0\r\n") :] + bytes(after))
    assert len(resumed) >= 3 and {s.temps_c["sensor"] for s in resumed} == {2500.0}  # 0.01 degC words now


def test_empty_setup_sends_and_reads_nothing() -> None:
    with PtyPair() as pair:
        port = open_port(pair.slave_path, timeout_s=0.05)
        try:
            pair.write(b"\xfe\x81\xff\x55 stays in the port")
            result = run_setup(port, DeviceSetup(()))
            assert port.read(64) == b"\xfe\x81\xff\x55 stays in the port"
        finally:
            port.close()
        assert pair.read_available(0.0) == b""
    assert (result.raw, result.replies, result.sent) == (b"", (), ())


def test_device_that_never_answers_is_a_one_line_error_within_the_deadline() -> None:
    with PtyPair() as pair:  # nothing on the master side: a device that is off
        port = open_port(pair.slave_path, timeout_s=0.05)
        try:
            pair.write(b"\x00\x01noise\r\n")  # bytes that arrive while waiting must be kept
            t0 = time.monotonic()
            with pytest.raises(DeviceSetupError) as info:
                run_setup(port, DeviceSetup(("=TEMPUNITS,C",), reply_timeout_s=0.2))
            elapsed_s = time.monotonic() - t0
        finally:
            port.close()
        sent = bytearray()
        while len(sent) < len(b"=CONFIG,1\r\n=CONFIG,0\r\n") and (chunk := pair.read_available(GUARD_S)):
            sent += chunk
        assert pair.read_available(0.0) == b""
    # nothing sent after the unanswered command but the way out of config mode
    assert bytes(sent) == b"=CONFIG,1\r\n=CONFIG,0\r\n"
    message = str(info.value)
    assert message == "no reply 'CONFIG,1' from the device to '=CONFIG,1' within 0.2 s (last line: 'noise')"
    assert 0.2 <= elapsed_s < 1.0
    assert info.value.raw == b"\x00\x01noise\r\n"


def test_refused_command_names_it_and_leaves_config_mode(device: tuple[PtyPair, FakeKvhDevice]) -> None:
    pair, dev = device
    port = open_port(pair.slave_path, timeout_s=0.05)
    try:
        with pytest.raises(DeviceSetupError) as info:
            run_setup(port, DeviceSetup(("=TEMPUNITS,C_100", "=TEMPUNITS,KELVIN", "=DR,100")))
    finally:
        port.close()
    assert str(info.value) == "the device refused '=TEMPUNITS,KELVIN': 'INVALID,=TEMPUNITS,KELVIN'"
    handled = [dev.commands.get(timeout=GUARD_S) for _ in range(4)]
    assert handled == ["=CONFIG,1", "=TEMPUNITS,C_100", "=TEMPUNITS,KELVIN", "=CONFIG,0"]  # =DR,100 never sent
    assert (dev.config_mode, dev.settings["DR"]) == (False, "1000")


# ---------------------------------------------------------------------------------------------
# PortReader's on_open hook


def test_reader_runs_setup_on_first_open_and_again_after_an_unplug(tmp_path: Path) -> None:
    link = tmp_path / "ttyKVH"
    setup = DeviceSetup(("=TEMPUNITS,C_100", "=ROTFMT,RATE"))
    results: list[SetupResult] = []
    with PtyPair() as pair1, FakeKvhDevice(pair1, frames_before_config=1) as dev1:
        pair1.symlink(link)
        rec = Reader(
            str(link), backoff_initial_s=0.01, backoff_max_s=0.02, on_open=make_on_open(setup, on_result=results.append)
        )
        try:
            events, _ = rec.until_state("open")
            assert [e.state for e in events] == ["opening", "open"]
            assert len(results) == 1  # the setup ran before "open" was reported
            assert rec.next_item() == ("data", results[0].raw)  # the setup's bytes come first, as one chunk
            assert dev1.settings["TEMPUNITS"] == "C_100" and dev1.settings["ROTFMT"] == "RATE"
            dev1.unplug()
            events, _ = rec.until_state("lost")
            pair1.close()  # removes the link: reopening fails until the "device" comes back
            with PtyPair() as pair2, FakeKvhDevice(pair2, frames_before_config=0) as dev2:
                pair2.symlink(link)
                events, _ = rec.until_state("open")
                assert events[0].state == "retry_wait" and events[-1].state == "open"
                assert len(results) == 2
                assert rec.next_item() == ("data", results[1].raw)
                assert bytes(dev2.received) == b"=CONFIG,1\r\n=TEMPUNITS,C_100\r\n=ROTFMT,RATE\r\n=CONFIG,0\r\n"
                assert dev2.settings["TEMPUNITS"] == "C_100" and not dev2.config_mode
                rec.join()  # stopped before the device goes: no second loss
        finally:
            rec.finish()
    assert (rec.reader.opens, rec.reader.losses) == (2, 1)
    assert results[0].raw.startswith(b"\xfe\x81\xff\x55") and results[0].replies[-1] == "CONFIG,0"
    assert results[1].raw.startswith(b"CONFIG,1\r\nTEMPUNITS,C_100\r\nROTFMT,RATE\r\nCONFIG,0\r\n")
    assert results[1].raw == bytes(dev2.sent)[: len(results[1].raw)]


def test_setup_failure_on_open_is_reported_like_a_failed_open() -> None:
    setup = DeviceSetup(("=DR,100",), reply_timeout_s=0.05)
    with PtyPair() as pair:  # nobody answers
        rec = Reader(pair.slave_path, backoff_initial_s=0.01, backoff_max_s=0.01, on_open=make_on_open(setup))
        try:
            events, data = rec.until_state("retry_wait")
            _, data2 = rec.until_state("retry_wait")  # and retried with the backoff
        finally:
            rec.finish()
    assert [e.state for e in events] == ["opening", "retry_wait"]  # never "open"
    assert events[-1].detail == (
        f"setup of {pair.slave_path} failed: no reply 'CONFIG,1' from the device to '=CONFIG,1' within 0.05 s"
        " (nothing received)"
    )
    assert (data, data2) == (b"", b"")
    assert rec.reader.opens == 0 and rec.reader.open_failures >= 2


@pytest.mark.parametrize("kwargs", [{"first_open": "fail"}, {"reconnect": False}])
def test_setup_failure_on_first_open_follows_first_open(kwargs: dict[str, object]) -> None:
    setup = DeviceSetup(("=DR,100",), reply_timeout_s=0.05)
    events: list[PortEvent] = []
    with PtyPair() as pair:
        reader = PortReader(pair.slave_path, on_state=events.append, on_open=make_on_open(setup), **kwargs)  # type: ignore[arg-type]
        with pytest.raises(PortError, match=r"setup of .* failed: no reply 'CONFIG,1' .* to '=CONFIG,1'"):
            list(reader.chunks(threading.Event()))
    assert [e.state for e in events] == ["opening", "closed"]
    assert (reader.opens, reader.open_failures) == (0, 1)
