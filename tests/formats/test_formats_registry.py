"""The format registry's sniffer tells every format apart from its bytes, garbage before them or not."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from fog_driver.errors import InputFileError
from fog_driver.formats.kvh import encode_kvh_frame
from fog_driver.formats.registry import FORMATS, MIN_FRAMES, sniff
from fog_driver.protocol import encode_identity, encode_sample
from fog_driver.samples.captures import inspect_capture

DATA = Path(__file__).parents[1] / "data"


def fog_v1(n: int) -> bytes:
    return encode_identity("FOG-1", 0x0102, 100, 0.01) + b"".join(
        encode_sample(k, 10_000 * k, k, 5000, 5001, 5002, 0) for k in range(n)
    )


def kvh(fmt: str, n: int) -> bytes:
    return b"".join(encode_kvh_frame(fmt, (1e-6, 2e-6, 3e-6), (0.0, 0.0, 1.0), seq=k % 128, temp=30) for k in range(n))


STREAMS = {
    "fog-v1": lambda: fog_v1(50),
    "kvh-a": lambda: kvh("a", 50),
    "kvh-b": lambda: kvh("b", 50),
    "kvh-c": lambda: kvh("c", 50),
    # real telegrams: iXblue's own capture (tests/data/ixblue/README.md says where from)
    "ixblue-stdbin": lambda: (DATA / "ixblue" / "log_STDBIN_V3.log").read_bytes(),
}


@pytest.mark.parametrize("name", sorted(STREAMS))
def test_every_format_is_told_apart_with_garbage_before_it(name):
    assert set(STREAMS) == set(FORMATS)
    garbage = random.Random(1).randbytes(300)
    for data in (STREAMS[name](), garbage + STREAMS[name]()):
        seen = sniff(data)
        assert seen.name == name, seen
        assert all(n == 0 for other, n in seen.frames.items() if other != name)
        assert seen.describe().startswith(f"{name} (") and "valid frames in the first" in seen.describe()


def test_random_bytes_and_a_single_frame_in_a_long_stream_are_no_verdict():
    noise = random.Random(2).randbytes(20_000)
    assert sniff(noise).name is None and sniff(noise).describe() == "no known format in the first 20,000 bytes"
    lonely = noise[:1000] + kvh("a", 1) + noise[1000:]
    assert MIN_FRAMES == 2 and sniff(lonely, limit=len(lonely) - 1).name is None
    assert "kvh-a 1, too few to tell" in sniff(lonely, limit=len(lonely) - 1).describe()


def test_inspect_names_what_a_capture_of_another_format_is(tmp_path):
    capture = tmp_path / "kvh.bin"
    capture.write_bytes(kvh("a", 200))
    with pytest.raises(InputFileError) as info:
        inspect_capture(capture)
    message = str(info.value)
    assert message == (
        f"{capture}: not a protocol v1 capture: no valid frame in 7200 bytes; it looks like kvh-a "
        "(200 valid frames in the first 7,200 bytes): read it with --format kvh-a or auto"
    )
