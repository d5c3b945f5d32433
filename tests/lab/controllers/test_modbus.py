"""The Modbus codec against the specifications' own frames, and against pymodbus's framers as an independent
reference: function 3 and 16 requests and replies, exception replies, MBAP with its transaction id, RTU with its
CRC; every split point of a reply, garbage and truncated replies.

The example frames are those of the Modbus Application Protocol Specification V1.1b3 (sections 6.3, 6.12 and
7) and the CRC example of the Modbus over Serial Line Specification V1.02 (Appendix B: frame 02 07, CRC 0x1241).
"""

from __future__ import annotations

import struct

import pymodbus.framer as pymodbus_framer
import pymodbus.pdu as pymodbus_pdu
import pytest
from pymodbus.pdu.register_message import ReadHoldingRegistersRequest, WriteMultipleRegistersRequest

from fog_driver.lab.controllers.base import ControllerProtocolError
from fog_driver.lab.controllers.codecs import modbus

SPEC_READ_REQUEST = bytes.fromhex("03 00 6B 00 03")
SPEC_READ_REPLY = bytes.fromhex("03 06 02 2B 00 00 00 64")
SPEC_WRITE_REQUEST = bytes.fromhex("10 00 01 00 02 04 00 0A 01 02")
SPEC_WRITE_REPLY = bytes.fromhex("10 00 01 00 02")
SPEC_EXCEPTION_REPLY = bytes.fromhex("83 02")


def _pymodbus_tcp(request) -> bytes:
    return pymodbus_framer.FramerSocket(pymodbus_pdu.DecodePDU(False)).buildFrame(request)


def _pymodbus_rtu(request) -> bytes:
    return pymodbus_framer.FramerRTU(pymodbus_pdu.DecodePDU(False)).buildFrame(request)


def test_a_read_of_three_registers_from_108_is_the_specifications_request():
    assert modbus.read_holding_request(0x6B, 3) == SPEC_READ_REQUEST


def test_the_specifications_read_reply_gives_its_three_register_values():
    assert modbus.decode_read_holding_reply(SPEC_READ_REPLY, 0x6B, 3) == (0x022B, 0x0000, 0x0064)


def test_a_write_of_two_registers_is_the_specifications_request_and_its_echo_is_accepted():
    assert modbus.write_multiple_request(1, [0x000A, 0x0102]) == SPEC_WRITE_REQUEST
    modbus.decode_write_multiple_reply(SPEC_WRITE_REPLY, 1, 2)


def test_a_write_echoing_another_address_or_count_is_refused():
    with pytest.raises(ControllerProtocolError, match="does not echo"):
        modbus.decode_write_multiple_reply(bytes.fromhex("10 00 02 00 02"), 1, 2)
    with pytest.raises(ControllerProtocolError, match="does not echo"):
        modbus.decode_write_multiple_reply(bytes.fromhex("10 00 01 00 01"), 1, 2)


def test_the_specifications_exception_reply_names_the_exception_on_one_line():
    with pytest.raises(modbus.ModbusExceptionReply) as caught:
        modbus.decode_read_holding_reply(SPEC_EXCEPTION_REPLY, 0x6B, 3)
    assert caught.value.code == 2 and caught.value.function == 3
    message = str(caught.value)
    assert "illegal data address" in message and "\n" not in message


@pytest.mark.parametrize(
    ("code", "name"),
    [(1, "illegal function"), (2, "illegal data address"), (3, "illegal data value"), (4, "server device failure")],
)
def test_each_exception_to_a_write_is_named(code, name):
    with pytest.raises(modbus.ModbusExceptionReply, match=name):
        modbus.decode_write_multiple_reply(bytes([0x90, code]), 1, 2)


def test_a_reply_of_another_function_or_a_wrong_byte_count_is_garbage():
    with pytest.raises(ControllerProtocolError, match="function 16"):
        modbus.decode_read_holding_reply(SPEC_WRITE_REPLY, 0x6B, 3)
    with pytest.raises(ControllerProtocolError, match="byte count"):
        modbus.decode_read_holding_reply(bytes.fromhex("03 04 02 2B 00 00"), 0x6B, 3)
    with pytest.raises(ControllerProtocolError):
        modbus.decode_read_holding_reply(SPEC_READ_REPLY[:-1], 0x6B, 3)
    with pytest.raises(ControllerProtocolError):
        modbus.decode_read_holding_reply(b"", 0x6B, 3)


def test_requests_beyond_the_protocols_limits_are_refused_before_any_byte():
    for address, count in ((0, 0), (0, 126), (65535, 2), (-1, 1)):
        with pytest.raises(ValueError):
            modbus.read_holding_request(address, count)
    with pytest.raises(ValueError):
        modbus.write_multiple_request(0, [0x10000])


def test_the_serial_specifications_crc_example():
    assert modbus.crc16(bytes.fromhex("02 07")) == 0x1241
    assert modbus.RtuFramer(2).request(bytes([7]))[-2:] == bytes.fromhex("41 12")  # low byte first


@pytest.mark.parametrize(("address", "count", "unit"), [(0x6B, 3, 17), (2782, 2, 1), (16568, 1, 247)])
def test_read_requests_are_framed_as_pymodbus_frames_them(address, count, unit):
    pdu = modbus.read_holding_request(address, count)
    assert modbus.RtuFramer(unit).request(pdu) == _pymodbus_rtu(
        ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit)
    )
    tcp = modbus.TcpFramer(unit)
    frame = tcp.request(pdu)
    assert frame == _pymodbus_tcp(
        ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit, transaction_id=tcp.expected_id)
    )


def test_write_requests_are_framed_as_pymodbus_frames_them():
    values = [0x000A, 0x0102]
    pdu = modbus.write_multiple_request(1, values)
    reference = WriteMultipleRegistersRequest(address=1, registers=values, dev_id=1)
    assert modbus.RtuFramer(1).request(pdu) == _pymodbus_rtu(reference)
    tcp = modbus.TcpFramer(1)
    tcp.request(pdu)
    second = tcp.request(pdu)
    reference.transaction_id = 2
    assert second == _pymodbus_tcp(reference)


def _tcp_reply(transaction_id: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", transaction_id, protocol, len(pdu) + 1, unit) + pdu


def _rtu_reply(unit: int, pdu: bytes) -> bytes:
    body = bytes([unit]) + pdu
    return body + struct.pack("<H", modbus.crc16(body))


def _framers_and_replies():
    tcp = modbus.TcpFramer(1)
    tcp.request(SPEC_READ_REQUEST)
    yield "tcp-read", tcp, _tcp_reply(tcp.expected_id, 1, SPEC_READ_REPLY), SPEC_READ_REPLY
    tcp_exc = modbus.TcpFramer(1)
    tcp_exc.request(SPEC_READ_REQUEST)
    yield "tcp-exception", tcp_exc, _tcp_reply(1, 1, SPEC_EXCEPTION_REPLY), SPEC_EXCEPTION_REPLY
    rtu = modbus.RtuFramer(17)
    yield "rtu-read", rtu, _rtu_reply(17, SPEC_READ_REPLY), SPEC_READ_REPLY
    yield "rtu-write", rtu, _rtu_reply(17, SPEC_WRITE_REPLY), SPEC_WRITE_REPLY
    yield "rtu-exception", rtu, _rtu_reply(17, SPEC_EXCEPTION_REPLY), SPEC_EXCEPTION_REPLY


CASES = list(_framers_and_replies())


@pytest.mark.parametrize(("framer", "frame", "pdu"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_reply_split_at_any_point_or_byte_by_byte_gives_the_same_pdu(framer, frame, pdu):
    for split in range(1, len(frame)):
        assembler = modbus.ReplyAssembler(framer)
        assert assembler.feed(frame[:split]) is None
        assert assembler.feed(frame[split:]) == pdu
    assembler = modbus.ReplyAssembler(framer)
    fed = [assembler.feed(frame[i : i + 1]) for i in range(len(frame))]
    assert fed[:-1] == [None] * (len(frame) - 1) and fed[-1] == pdu


def test_a_tcp_reply_to_another_transaction_is_refused():
    framer = modbus.TcpFramer(1)
    framer.request(SPEC_READ_REQUEST)
    framer.request(SPEC_READ_REQUEST)  # the reply to the first is now late
    with pytest.raises(ControllerProtocolError, match="transaction id 1 to request 2"):
        modbus.ReplyAssembler(framer).feed(_tcp_reply(1, 1, SPEC_READ_REPLY))


def test_transaction_ids_wrap_after_65535():
    framer = modbus.TcpFramer(1)
    ids = []
    for _ in range(65537):
        framer.request(SPEC_READ_REQUEST)
        ids.append(framer.expected_id)
    assert ids[0] == 1 and ids[65534] == 65535 and ids[65535] == 0 and ids[65536] == 1


def test_a_tcp_reply_from_another_unit_or_protocol_or_length_is_garbage():
    framer = modbus.TcpFramer(1)
    framer.request(SPEC_READ_REQUEST)
    with pytest.raises(ControllerProtocolError, match="unit 2"):
        modbus.ReplyAssembler(framer).feed(_tcp_reply(1, 2, SPEC_READ_REPLY))
    with pytest.raises(ControllerProtocolError, match="protocol id 7"):
        modbus.ReplyAssembler(framer).feed(_tcp_reply(1, 1, SPEC_READ_REPLY, protocol=7))
    with pytest.raises(ControllerProtocolError, match="length 0"):
        modbus.ReplyAssembler(framer).feed(bytes.fromhex("00 01 00 00 00 00 01"))
    with pytest.raises(ControllerProtocolError, match="length 1000"):
        modbus.ReplyAssembler(framer).feed(struct.pack(">HHHB", 1, 0, 1000, 1))


def test_bytes_after_a_whole_reply_are_garbage():
    framer = modbus.RtuFramer(17)
    with pytest.raises(ControllerProtocolError, match="after a Modbus reply"):
        modbus.ReplyAssembler(framer).feed(_rtu_reply(17, SPEC_READ_REPLY) + b"\x00")


def test_an_rtu_reply_with_a_flipped_bit_or_from_another_unit_is_refused():
    frame = bytearray(_rtu_reply(17, SPEC_READ_REPLY))
    frame[4] ^= 0x01
    with pytest.raises(ControllerProtocolError, match="CRC"):
        modbus.ReplyAssembler(modbus.RtuFramer(17)).feed(bytes(frame))
    with pytest.raises(ControllerProtocolError, match="unit 18"):
        modbus.ReplyAssembler(modbus.RtuFramer(17)).feed(_rtu_reply(18, SPEC_READ_REPLY))


def test_an_rtu_reply_of_an_unexpected_function_is_garbage_at_its_third_byte():
    with pytest.raises(ControllerProtocolError, match="function 6"):
        modbus.ReplyAssembler(modbus.RtuFramer(1)).feed(bytes.fromhex("01 06 00"))


def test_a_truncated_reply_stays_incomplete_and_a_frame_cut_short_is_refused():
    framer = modbus.TcpFramer(1)
    framer.request(SPEC_READ_REQUEST)
    whole = _tcp_reply(1, 1, SPEC_READ_REPLY)
    assert modbus.ReplyAssembler(framer).feed(whole[:-1]) is None
    with pytest.raises(ControllerProtocolError):
        framer.reply(whole[:-1])
    with pytest.raises(ControllerProtocolError):
        modbus.RtuFramer(1).reply(b"\x01\x03")
