"""Modbus as bytes (sans-IO): the two requests a chamber driver needs and their replies, framed for TCP or RTU.

From the Modbus Application Protocol Specification V1.1b3 (modbus.org): function 3 (read holding registers) and
function 16 (write multiple registers), and the exception reply (the function with bit 0x80 set, then one
exception code).  Function 6 (write a single register) is never sent: a 32-bit float written as two single
registers would be half old, half new in between, and the F4T's manual asks for function 16.

Framing:

- TCP (Modbus Messaging on TCP/IP Implementation Guide V1.0b): a 7-byte MBAP header (transaction id, protocol id
  0, the length of what follows, the unit id) before the PDU.  A reply must carry the transaction id of its
  request, protocol 0 and the unit asked (``TcpFramer``);
- RTU (Modbus over Serial Line Specification V1.02): the unit id, the PDU and a CRC-16 (polynomial 0xA001
  reflected, initial 0xFFFF, sent low byte first).  A reply whose CRC does not match is garbage (``RtuFramer``).

A framer makes the request frame (``request``), says how long the reply frame is from what has arrived so far
(``bytes_needed``), and checks a whole reply frame, returning its PDU (``reply``).  The PDU decoders then check
the function, the byte count, the echo of a write.  Everything wrong in a reply is a one-line
``ControllerProtocolError`` (an exception reply: ``ModbusExceptionReply``, naming the exception).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Protocol

from ..base import ControllerProtocolError

READ_HOLDING_REGISTERS = 3
WRITE_MULTIPLE_REGISTERS = 16
EXCEPTION_BIT = 0x80
#: The most registers one request may read (125) or write (123), per the application protocol.
MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 123

FUNCTION_NAMES = {
    READ_HOLDING_REGISTERS: "read holding registers",
    WRITE_MULTIPLE_REGISTERS: "write multiple registers",
}

#: Exception codes (Modbus Application Protocol Specification V1.1b3, section 7).
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}

MBAP_BYTES = 7
#: The MBAP length field counts the unit id and the PDU: a PDU is 1..253 bytes.
MAX_PDU_BYTES = 253
RTU_MIN_HEAD = 3  # unit, function, then a byte count or an exception code


class ModbusExceptionReply(ControllerProtocolError):
    """The controller answered a Modbus exception (``code``) to ``function``."""

    def __init__(self, message: str, *, function: int, code: int) -> None:
        super().__init__(message)
        self.function = function
        self.code = code


def _describe(function: int) -> str:
    return f"function {function} ({FUNCTION_NAMES.get(function, 'unknown')})"


def _check_registers(address: int, count: int, most: int) -> None:
    if not 0 <= address <= 0xFFFF:
        raise ValueError(f"register address {address} is not 0..65535")
    if not 1 <= count <= most or address + count > 0x10000:
        raise ValueError(f"{count} registers from {address}: not 1..{most} within 0..65535")


def read_holding_request(address: int, count: int) -> bytes:
    """The PDU reading ``count`` holding registers from protocol (0-based) ``address``."""
    _check_registers(address, count, MAX_READ_REGISTERS)
    return struct.pack(">BHH", READ_HOLDING_REGISTERS, address, count)


def write_multiple_request(address: int, values: Sequence[int]) -> bytes:
    """The PDU writing ``values`` (each 0..65535) to the holding registers from ``address``."""
    _check_registers(address, len(values), MAX_WRITE_REGISTERS)
    if any(not 0 <= v <= 0xFFFF for v in values):
        raise ValueError("a register holds 0..65535")
    return struct.pack(f">BHHB{len(values)}H", WRITE_MULTIPLE_REGISTERS, address, len(values), 2 * len(values), *values)


def _check_exception(pdu: bytes, function: int, address: int) -> None:
    if not pdu:
        raise ControllerProtocolError(f"an empty Modbus reply to {_describe(function)}")
    if pdu[0] == function | EXCEPTION_BIT:
        if len(pdu) != 2:
            raise ControllerProtocolError(f"a Modbus exception reply of {len(pdu)} bytes (2 expected): {pdu.hex(' ')}")
        code = pdu[1]
        name = EXCEPTION_NAMES.get(code, "an exception code the specification does not define")
        raise ModbusExceptionReply(
            f"the controller answered Modbus exception {code} ({name}) to {_describe(function)} at register {address}",
            function=function,
            code=code,
        )
    if pdu[0] != function:
        raise ControllerProtocolError(f"a Modbus reply of function {pdu[0]} to {_describe(function)}: {pdu.hex(' ')}")


def decode_read_holding_reply(pdu: bytes, address: int, count: int) -> tuple[int, ...]:
    """The ``count`` register values of a function 3 reply (``address``: for messages)."""
    _check_exception(pdu, READ_HOLDING_REGISTERS, address)
    if len(pdu) < 2 or pdu[1] != 2 * count or len(pdu) != 2 + 2 * count:
        raise ControllerProtocolError(
            f"a read holding registers reply of {len(pdu)} bytes for {count} registers (byte count "
            f"{pdu[1] if len(pdu) > 1 else 'missing'}): {pdu[:16].hex(' ')}"
        )
    return struct.unpack(f">{count}H", pdu[2:])


def decode_write_multiple_reply(pdu: bytes, address: int, count: int) -> None:
    """Check a function 16 reply echoes the address and count written."""
    _check_exception(pdu, WRITE_MULTIPLE_REGISTERS, address)
    expected = struct.pack(">BHH", WRITE_MULTIPLE_REGISTERS, address, count)
    if pdu != expected:
        raise ControllerProtocolError(
            f"a write multiple registers reply {pdu[:16].hex(' ')} does not echo {expected.hex(' ')}"
        )


class Framer(Protocol):
    """A Modbus transport's framing: request frames out, reply frames checked."""

    def request(self, pdu: bytes) -> bytes:
        """The frame carrying ``pdu``; the framer then expects its reply."""

    def bytes_needed(self, received: bytes) -> int:
        """The length of the whole reply frame as far as ``received`` (its start) tells; more than
        ``len(received)`` while the frame is incomplete.  Garbage: ``ControllerProtocolError``."""

    def reply(self, frame: bytes) -> bytes:
        """The PDU of a whole reply frame, checked against the request."""


class TcpFramer:
    """MBAP framing for ``unit``; transaction ids count up from 1 (mod 65536), each reply must carry its own."""

    def __init__(self, unit: int) -> None:
        if not 0 <= unit <= 255:
            raise ValueError(f"unit {unit} is not 0..255")
        self.unit = unit
        self._transaction_id = 0
        self.expected_id: int | None = None

    def request(self, pdu: bytes) -> bytes:
        if not 1 <= len(pdu) <= MAX_PDU_BYTES:
            raise ValueError(f"a PDU of {len(pdu)} bytes")
        self._transaction_id = (self._transaction_id + 1) & 0xFFFF
        self.expected_id = self._transaction_id
        return struct.pack(">HHHB", self._transaction_id, 0, len(pdu) + 1, self.unit) + pdu

    def bytes_needed(self, received: bytes) -> int:
        if len(received) < MBAP_BYTES:
            return MBAP_BYTES
        protocol: int
        length: int
        _tid, protocol, length, _unit = struct.unpack(">HHHB", received[:MBAP_BYTES])
        if protocol != 0:
            raise ControllerProtocolError(f"a Modbus TCP reply with protocol id {protocol} (0 expected)")
        if not 2 <= length <= MAX_PDU_BYTES + 1:
            raise ControllerProtocolError(f"a Modbus TCP reply with length {length} (2..{MAX_PDU_BYTES + 1} expected)")
        return 6 + length

    def reply(self, frame: bytes) -> bytes:
        if len(frame) != self.bytes_needed(frame):
            raise ControllerProtocolError(
                f"a Modbus TCP reply of {len(frame)} bytes, not the {self.bytes_needed(frame)} it says"
            )
        tid, _protocol, _length, unit = struct.unpack(">HHHB", frame[:MBAP_BYTES])
        if tid != self.expected_id:
            raise ControllerProtocolError(
                f"a Modbus TCP reply with transaction id {tid} to request {self.expected_id} (another's reply)"
            )
        if unit != self.unit:
            raise ControllerProtocolError(f"a Modbus TCP reply from unit {unit} (unit {self.unit} was asked)")
        return frame[MBAP_BYTES:]


def crc16(data: bytes) -> int:
    """Modbus RTU's CRC-16: polynomial 0xA001 (reflected 0x8005), initial 0xFFFF; sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


class RtuFramer:
    """RTU framing for ``unit`` (1..247): the unit id, the PDU, the CRC (low byte first)."""

    def __init__(self, unit: int) -> None:
        if not 1 <= unit <= 247:
            raise ValueError(f"unit {unit} is not 1..247 (a serial line's server addresses)")
        self.unit = unit

    def request(self, pdu: bytes) -> bytes:
        if not 1 <= len(pdu) <= MAX_PDU_BYTES:
            raise ValueError(f"a PDU of {len(pdu)} bytes")
        body = bytes([self.unit]) + pdu
        return body + struct.pack("<H", crc16(body))

    def bytes_needed(self, received: bytes) -> int:
        if len(received) < RTU_MIN_HEAD:
            return RTU_MIN_HEAD
        function = received[1]
        if function & EXCEPTION_BIT:
            return 5  # unit, function | 0x80, code, CRC
        if function == READ_HOLDING_REGISTERS:
            return 3 + received[2] + 2
        if function == WRITE_MULTIPLE_REGISTERS:
            return 8  # unit, function, address, count, CRC
        raise ControllerProtocolError(f"a Modbus RTU reply of function {function}: {received[:16].hex(' ')}")

    def reply(self, frame: bytes) -> bytes:
        if len(frame) < 4:
            raise ControllerProtocolError(f"a Modbus RTU reply of {len(frame)} bytes")
        (crc,) = struct.unpack("<H", frame[-2:])
        if crc != crc16(frame[:-2]):
            raise ControllerProtocolError(f"a Modbus RTU reply whose CRC does not match: {frame[:16].hex(' ')}")
        if frame[0] != self.unit:
            raise ControllerProtocolError(f"a Modbus RTU reply from unit {frame[0]} (unit {self.unit} was asked)")
        return frame[1:-2]


class ReplyAssembler:
    """A reply frame put together from whatever pieces it arrives in: ``feed`` returns its PDU once whole
    (``None`` until then); bytes beyond the frame are garbage."""

    def __init__(self, framer: Framer) -> None:
        self.framer = framer
        self._buffer = bytearray()

    def feed(self, data: bytes) -> bytes | None:
        self._buffer += data
        needed = self.framer.bytes_needed(bytes(self._buffer))
        if len(self._buffer) > needed:
            raise ControllerProtocolError(f"{len(self._buffer) - needed} bytes after a Modbus reply")
        if len(self._buffer) < needed:
            return None
        frame = bytes(self._buffer)
        self._buffer.clear()
        return self.framer.reply(frame)
