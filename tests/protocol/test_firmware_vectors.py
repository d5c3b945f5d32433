"""The C reference encoder in ``firmware_protocol/c`` against the committed golden
vectors and against the Python codec.

The C sources are compiled here with the system compiler (``$CC`` or ``cc``,
warnings as errors), the vector generator is run into a temporary directory and
its output must be byte-identical to ``firmware_protocol/vectors``.  The
listing ``golden.txt`` is then parsed and checked three ways against
``golden.bin``: its hex, the Python decoders (streaming, one byte at a time,
and batch) and the Python encoders.  No expected values are written here apart
from the published CRC-32/ISO-HDLC check value.
"""

from __future__ import annotations

import os
import random
import re
import shlex
import shutil
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from fog_driver.protocol import (
    FrameDecoder,
    IdentityFrame,
    SampleFrame,
    UnknownFrame,
    crc32,
    decode_bytes,
    encode_frame,
    encode_identity,
    encode_sample,
)
from fog_driver.protocol.crc import ISO_HDLC_TABLE, crc32_reference, crc32_rows

ROOT = Path(__file__).resolve().parents[2]
C_DIR = ROOT / "firmware_protocol" / "c"
VECTORS = ROOT / "firmware_protocol" / "vectors"
GOLDEN_BIN = VECTORS / "golden.bin"
GOLDEN_TXT = VECTORS / "golden.txt"

WARNING_FLAGS = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror"]
CRC_CHECK_VALUE = 0xCBF43926  # published check value of CRC-32/ISO-HDLC over b"123456789"


# ---------------------------------------------------------------------------
# Building and running the C code


def _compiler() -> list[str]:
    cc = os.environ.get("CC", "").strip()
    if cc:
        argv = shlex.split(cc)
        found = shutil.which(argv[0])
        if found is None:
            pytest.fail(f"$CC is set to {cc!r} but {argv[0]!r} is not on PATH; a C compiler is required")
        return [found, *argv[1:]]
    for name in ("cc", "gcc", "clang"):
        found = shutil.which(name)
        if found is not None:
            return [found]
    pytest.fail(
        "no C compiler found (set $CC or install cc/gcc/clang): the firmware reference encoder "
        "in firmware_protocol/c must be compiled to check the golden vectors"
    )


def _run(argv: list[str], **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, timeout=120, **kwargs)


@pytest.fixture(scope="module")
def generator(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``make_vectors`` built from the committed sources, warnings as errors."""
    out = tmp_path_factory.mktemp("fog_c") / "make_vectors"
    argv = [*_compiler(), *WARNING_FLAGS, "-o", str(out), str(C_DIR / "make_vectors.c"), str(C_DIR / "fog_protocol.c")]
    result = _run(argv)
    assert result.returncode == 0, f"compile failed: {shlex.join(argv)}\n{result.stderr.decode(errors='replace')}"
    assert result.stderr.strip() == b"", f"compiler printed diagnostics:\n{result.stderr.decode(errors='replace')}"
    return out


@pytest.fixture(scope="module")
def generated(generator: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, bytes]:
    """(golden.bin, golden.txt) as the generator writes them now."""
    out = tmp_path_factory.mktemp("fog_vectors")
    result = _run([str(generator), str(out / "golden.bin"), str(out / "golden.txt")])
    assert result.returncode == 0, (
        f"make_vectors failed ({result.returncode}): {result.stderr.decode(errors='replace')}"
    )
    assert result.stderr == b""
    return (out / "golden.bin").read_bytes(), (out / "golden.txt").read_bytes()


# ---------------------------------------------------------------------------
# Parsing golden.txt

_LINE = re.compile(r"(SAMPLE|IDENTITY|FRAME) (.*?) \| ([0-9a-f]{2}(?: [0-9a-f]{2})*)")
_FIELD = re.compile(r'(\w+)=("[^"\\]*"|[^\s"]*)')
_FIELDS = re.compile(r'\w+=(?:"[^"\\]*"|[^\s"]*)(?: \w+=(?:"[^"\\]*"|[^\s"]*))*')
_KEYS = {
    "SAMPLE": ["seq", "t_us", "dtheta", "t_top", "t_bottom", "t_housing", "status", "crc"],
    "IDENTITY": ["serial", "firmware", "rate_hz", "scale_bits", "scale", "crc"],
    "FRAME": ["type", "len", "payload", "crc"],
}


@dataclass(frozen=True)
class Entry:
    line_no: int
    kind: str
    fields: dict[str, str]
    frame: bytes

    def int(self, key: str) -> int:
        return int(self.fields[key], 0)

    @property
    def serial(self) -> str:
        value = self.fields["serial"]
        assert value.startswith('"') and value.endswith('"'), f"line {self.line_no}: serial not quoted"
        return value[1:-1]

    @property
    def scale_bits(self) -> bytes:
        return self.int("scale_bits").to_bytes(4, "little")

    @property
    def scale(self) -> float:
        return struct.unpack("<f", self.scale_bits)[0]

    @property
    def payload(self) -> bytes:
        return bytes.fromhex(self.fields["payload"])


def parse_listing(text: str) -> list[Entry]:
    entries = []
    for line_no, line in enumerate(text.splitlines(), 1):
        if line.startswith("#"):
            assert not entries, f"line {line_no}: comments are only allowed at the top"
            continue
        m = _LINE.fullmatch(line)
        assert m, f"line {line_no}: malformed: {line!r}"
        kind, field_text, hex_text = m.groups()
        assert _FIELDS.fullmatch(field_text), f"line {line_no}: malformed field list {field_text!r}"
        pairs = _FIELD.findall(field_text)
        keys = [k for k, _ in pairs]
        assert keys == _KEYS[kind], f"line {line_no}: fields {keys}, expected {_KEYS[kind]}"
        entries.append(Entry(line_no, kind, dict(pairs), bytes.fromhex(hex_text)))
    assert entries, "golden.txt lists no frames"
    return entries


@pytest.fixture(scope="module")
def golden_bin() -> bytes:
    return GOLDEN_BIN.read_bytes()


@pytest.fixture(scope="module")
def entries() -> list[Entry]:
    return parse_listing(GOLDEN_TXT.read_text(encoding="ascii"))


def expected_events(entries: list[Entry]) -> list[SampleFrame | IdentityFrame | UnknownFrame]:
    """The frames the listing says golden.bin holds, at their stream offsets."""
    events: list[SampleFrame | IdentityFrame | UnknownFrame] = []
    offset = 0
    for e in entries:
        if e.kind == "SAMPLE":
            events.append(
                SampleFrame(
                    offset,
                    e.int("seq"),
                    e.int("t_us"),
                    e.int("dtheta"),
                    e.int("t_top"),
                    e.int("t_bottom"),
                    e.int("t_housing"),
                    e.int("status"),
                )
            )
        elif e.kind == "IDENTITY":
            events.append(IdentityFrame(offset, e.serial, e.int("firmware"), e.int("rate_hz"), e.scale))
        else:
            events.append(UnknownFrame(offset, e.int("type"), e.payload))
        offset += len(e.frame)
    return events


def expected_counters(entries: list[Entry], total: int) -> dict[str, int]:
    seqs = [e.int("seq") for e in entries if e.kind == "SAMPLE"]
    t_us = [e.int("t_us") for e in entries if e.kind == "SAMPLE"]
    steps = [(b - a) % 65536 for a, b in zip(seqs, seqs[1:])]
    return {
        "bytes_in": total,
        "bytes_in_frames": total,
        "bytes_discarded": 0,
        "sample_frames": len(seqs),
        "identity_frames": sum(e.kind == "IDENTITY" for e in entries),
        "unknown_frames": sum(e.kind == "FRAME" for e in entries),
        "crc_errors": 0,
        "length_errors": 0,
        "truncated_frames": 0,
        "resyncs": 0,
        "seq_gaps": sum(s > 1 for s in steps),
        "missing_frames": sum(s - 1 for s in steps if s > 1),
        "seq_repeats": sum(s == 0 for s in steps),
        "t_us_wraps": sum(b < a for a, b in zip(t_us, t_us[1:])),
    }


def _shortest_f32_decimal(bits: bytes) -> str:
    """The shortest decimal that reads back as this binary32 (what a human would have written)."""
    value = struct.unpack("<f", bits)[0]
    for digits in range(1, 10):
        text = f"{value:.{digits}g}"
        if struct.pack("<f", float(text)) == bits:
            return text
    raise AssertionError(f"no decimal for {bits.hex()}")  # 9 digits always suffice


def _assert_events_equal(got, want) -> None:
    assert len(got) == len(want), f"{len(got)} frames decoded, {len(want)} listed"
    for g, w in zip(got, want):
        assert type(g) is type(w) and g == w, f"at offset {w.offset}: decoded {g!r}, listed {w!r}"
        if isinstance(w, IdentityFrame):
            # Bit-exact f32, not just float equality.
            assert struct.pack("<f", g.scale_arcsec_per_count) == struct.pack("<f", w.scale_arcsec_per_count)


# ---------------------------------------------------------------------------
# The C side


def test_encoder_compiles_alone_warning_free(tmp_path: Path) -> None:
    obj = tmp_path / "fog_protocol.o"
    argv = [*_compiler(), *WARNING_FLAGS, "-c", "-o", str(obj), str(C_DIR / "fog_protocol.c")]
    result = _run(argv)
    assert result.returncode == 0 and result.stderr.strip() == b"", result.stderr.decode(errors="replace")


def test_encoder_source_has_no_stdio_or_allocation() -> None:
    source = (C_DIR / "fog_protocol.c").read_text() + (C_DIR / "fog_protocol.h").read_text()
    code = re.sub(r"/\*.*?\*/|//[^\n]*", "", source, flags=re.S)  # comments may mention anything
    includes = set(re.findall(r"#\s*include\s*[<\"]([^>\"]+)[>\"]", code))
    assert includes <= {"fog_protocol.h", "stddef.h", "stdint.h", "string.h"}, includes
    for word in ("malloc", "calloc", "realloc", "free", "printf", "FILE", "stdio", "htonl", "htons"):
        assert not re.search(rf"\b{word}\b", code), f"encoder uses {word}"


def test_generator_output_is_the_committed_vectors(generated: tuple[bytes, bytes]) -> None:
    bin_now, txt_now = generated
    assert bin_now == GOLDEN_BIN.read_bytes(), "golden.bin is stale: run `make -C firmware_protocol/c vectors`"
    assert txt_now == GOLDEN_TXT.read_bytes(), "golden.txt is stale: run `make -C firmware_protocol/c vectors`"


def test_c_crc_check_value(generator: Path) -> None:
    result = _run([str(generator), "--crc-check"])
    assert result.returncode == 0, result.stderr.decode(errors="replace")
    c_crc = int(result.stdout.decode().strip(), 16)
    assert c_crc == CRC_CHECK_VALUE
    assert crc32(b"123456789") == CRC_CHECK_VALUE
    assert c_crc == crc32(b"123456789")


def test_c_crc_matches_python_on_random_data(generator: Path) -> None:
    rng = random.Random(20240601)
    for size in (0, 1, 2, 3, 255, 4095, 4096, 4097, 10000):
        data = bytes(rng.randrange(256) for _ in range(size))
        result = _run([str(generator), "--crc-stdin"], input=data)
        assert result.returncode == 0, result.stderr.decode(errors="replace")
        assert int(result.stdout.decode().strip(), 16) == crc32(data), f"{size} bytes"


def test_c_crc_table_is_the_crc_leaf_s() -> None:
    """The C encoder's 256-entry table, read from its source, is ``protocol.crc``'s, entry for entry."""
    source = (C_DIR / "fog_protocol.c").read_text()
    body = source.split("fog_crc32_table[256] = {", 1)[1].split("};", 1)[0]
    c_table = [int(word, 16) for word in re.findall(r"0x([0-9A-Fa-f]{8})ul", body)]
    assert len(c_table) == 256
    assert c_table == ISO_HDLC_TABLE.tolist()


def test_c_crc_matches_the_vector_forms_at_every_length(generator: Path) -> None:
    """``crc32_rows`` and the table reference against the C encoder, for every length 1..40 (odd and even)."""
    rng = np.random.default_rng(20261204)
    for m in range(1, 41):
        rows = rng.integers(0, 256, (3, m), dtype=np.uint8)
        c_crcs = []
        for row in rows:
            result = _run([str(generator), "--crc-stdin"], input=row.tobytes())
            assert result.returncode == 0, result.stderr.decode(errors="replace")
            c_crcs.append(int(result.stdout.decode().strip(), 16))
        assert crc32_rows(rows).tolist() == c_crcs, f"{m} bytes"
        assert [crc32_reference(row.tobytes()) for row in rows] == c_crcs, f"{m} bytes"


def test_generator_rejects_bad_usage(generator: Path) -> None:
    assert _run([str(generator)]).returncode == 2
    assert _run([str(generator), "--bogus"]).returncode == 2


# ---------------------------------------------------------------------------
# The listing against golden.bin and against the Python codec


def test_listing_hex_is_golden_bin(entries: list[Entry], golden_bin: bytes) -> None:
    assert b"".join(e.frame for e in entries) == golden_bin


def test_listing_lines_are_self_consistent(entries: list[Entry]) -> None:
    for e in entries:
        f = e.frame
        where = f"line {e.line_no}"
        assert f[:2] == b"\xaa\x55", where
        assert len(f) == 8 + f[3], where
        assert e.int("crc") == int.from_bytes(f[-4:], "little") == crc32(f[2:-4]), where
        if e.kind == "SAMPLE":
            assert f[2] == 0x01 and f[3] == 18, where
        elif e.kind == "IDENTITY":
            assert f[2] == 0x02 and f[3] == 24, where
            assert struct.pack("<f", float(e.fields["scale"])) == e.scale_bits, where
        else:
            assert f[2] == e.int("type") and f[3] == e.int("len") == len(e.payload), where
            assert f[4:-4] == e.payload, where


def test_streaming_decoder_one_byte_at_a_time(entries: list[Entry], golden_bin: bytes) -> None:
    decoder = FrameDecoder()
    events = []
    for i in range(len(golden_bin)):
        events += decoder.feed(golden_bin[i : i + 1])
    events += decoder.close()
    _assert_events_equal(events, expected_events(entries))
    assert decoder.counters.as_dict() == expected_counters(entries, len(golden_bin))
    assert decoder.pending == 0


def test_streaming_decoder_whole_stream(entries: list[Entry], golden_bin: bytes) -> None:
    decoder = FrameDecoder()
    events = decoder.feed(golden_bin)
    assert decoder.pending == 0  # every frame is complete: nothing is held back
    events += decoder.close()
    _assert_events_equal(events, expected_events(entries))
    assert decoder.counters.as_dict() == expected_counters(entries, len(golden_bin))


def test_batch_decoder(entries: list[Entry], golden_bin: bytes) -> None:
    decoded = decode_bytes(golden_bin)
    _assert_events_equal(decoded.events(), expected_events(entries))
    assert decoded.counters.as_dict() == expected_counters(entries, len(golden_bin))
    assert decoded.pending == 0


def test_python_encoders_emit_the_listed_bytes(entries: list[Entry]) -> None:
    for e in entries:
        if e.kind == "SAMPLE":
            got = encode_sample(
                e.int("seq"),
                e.int("t_us"),
                e.int("dtheta"),
                e.int("t_top"),
                e.int("t_bottom"),
                e.int("t_housing"),
                e.int("status"),
            )
        elif e.kind == "IDENTITY":
            got = encode_identity(e.serial, e.int("firmware"), e.int("rate_hz"), e.scale)
        else:
            got = encode_frame(e.int("type"), e.payload)
        assert got.hex(" ") == e.frame.hex(" "), f"line {e.line_no}: {e.kind} {e.fields}"


def test_vectors_cover_the_required_cases(entries: list[Entry]) -> None:
    """Guards the vector list itself: the edge cases the firmware must get right stay in it."""
    samples = [e for e in entries if e.kind == "SAMPLE"]
    identities = [e for e in entries if e.kind == "IDENTITY"]
    frames = [e for e in entries if e.kind == "FRAME"]
    seqs = [e.int("seq") for e in samples]
    t_us = [e.int("t_us") for e in samples]
    dthetas = {e.int("dtheta") for e in samples}
    statuses = {e.int("status") for e in samples}
    temps = {k: {e.int(k) for e in samples} for k in ("t_top", "t_bottom", "t_housing")}

    assert any(a == 65535 and b == 0 for a, b in zip(seqs, seqs[1:])), "seq wrap 65535 -> 0"
    assert any(b < a and a >= 2**32 - 10_000 for a, b in zip(t_us, t_us[1:])), "t_us wrap near 2^32"
    assert 2**32 - 1 in t_us
    assert {-(2**31), 2**31 - 1}.issubset(dthetas) and any(d < 0 for d in dthetas - {-(2**31)})
    for name, values in temps.items():
        assert -32768 in values, f"sentinel on {name}"
    assert {-32767, 32767}.issubset(temps["t_top"] | temps["t_bottom"] | temps["t_housing"])
    for bit in range(5):
        assert 1 << bit in statuses, f"status bit {bit} alone"
    assert any(s & 0xFFE0 for s in statuses), "a reserved status bit"

    serials = {e.serial for e in identities}
    assert any(len(s) == 16 for s in serials) and any(0 < len(s) < 16 for s in serials)
    assert 0x0102 in {e.int("firmware") for e in identities}
    assert {100, 1000}.issubset({e.int("rate_hz") for e in identities})
    scales = {e.scale for e in identities}
    assert len(scales) >= 3
    # at least one scale given as a short decimal that binary32 cannot hold exactly (0.017, 0.1)
    assert any(float(_shortest_f32_decimal(e.scale_bits)) != e.scale for e in identities)
    # IDENTITY between SAMPLE frames without advancing seq
    kinds = [e.kind for e in entries]
    for i in range(1, len(entries) - 1):
        if (
            kinds[i - 1 : i + 2] == ["SAMPLE", "IDENTITY", "SAMPLE"]
            and (entries[i + 1].int("seq") - entries[i - 1].int("seq")) % 65536 == 1
        ):
            break
    else:
        pytest.fail("no IDENTITY between consecutive SAMPLE frames")

    assert any(e.int("type") == 0x7E and e.int("len") > 0 for e in frames)
    assert any(e.int("len") == 0 for e in frames)
    # a false sync AA 55 inside a payload
    assert any(b"\xaa\x55" in e.frame[4:-4] for e in entries if e.kind == "SAMPLE")
    assert any(b"\xaa\x55" in e.frame[4:-4] for e in frames)


# ---------------------------------------------------------------------------
# PROTOCOL.md stays true

PROTOCOL_MD = ROOT / "firmware_protocol" / "PROTOCOL.md"


def _fenced_blocks(info: str) -> list[str]:
    return re.findall(rf"^```{info}\n(.*?)^```", PROTOCOL_MD.read_text(encoding="utf-8"), flags=re.S | re.M)


def test_protocol_md_hex_dumps_are_golden_frames(entries: list[Entry]) -> None:
    frames = {e.frame: e.kind for e in entries}
    dumps = [bytes.fromhex(block) for block in _fenced_blocks("hex")]
    kinds = []
    for dump in dumps:
        assert dump in frames, f"PROTOCOL.md hex dump is not a golden frame: {dump.hex(' ')}"
        kinds.append(frames[dump])
    assert "SAMPLE" in kinds and "IDENTITY" in kinds


def test_protocol_md_bitwise_crc_snippet(tmp_path: Path, golden_bin: bytes) -> None:
    (snippet,) = [b for b in _fenced_blocks("c") if "crc32_bitwise(const" in b]
    main = (
        "#include <stdio.h>\n"
        "int main(void) {\n"
        "    static uint8_t buf[1 << 16]; size_t n = fread(buf, 1, sizeof buf, stdin);\n"
        '    printf("%08lx %08lx\\n", (unsigned long)crc32_bitwise((const uint8_t *)"123456789", 9),\n'
        "           (unsigned long)crc32_bitwise(buf, n));\n"
        "    return 0;\n"
        "}\n"
    )
    (tmp_path / "snippet.c").write_text(snippet + main)
    exe = tmp_path / "snippet"
    result = _run([*_compiler(), *WARNING_FLAGS, "-o", str(exe), str(tmp_path / "snippet.c")])
    assert result.returncode == 0 and result.stderr.strip() == b"", result.stderr.decode(errors="replace")
    assert len(golden_bin) < 1 << 16
    result = _run([str(exe)], input=golden_bin)
    check, whole = (int(x, 16) for x in result.stdout.split())
    assert check == CRC_CHECK_VALUE
    assert whole == crc32(golden_bin)
