"""Wire protocol v1, sans-IO: encoders, the streaming ``FrameDecoder`` and the batch decoder."""

from .batch import (
    FILE_BLOCK_BYTES,
    BatchDecoder,
    DecodedCapture,
    SampleArrays,
    concatenate,
    decode_bytes,
    decode_file,
    iter_decode_file,
)
from .decoder import DecoderCounters, FrameDecoder, seq_step
from .wire import (
    IDENTITY_FRAME_LEN,
    MAX_FRAME_LEN,
    OVERHEAD_LEN,
    SAMPLE_FRAME_LEN,
    SEQ_MODULUS,
    STATUS_BIT_NAMES,
    STATUS_LIGHT_SOURCE_FAULT,
    STATUS_LOOP_UNLOCKED,
    STATUS_OVER_RANGE,
    STATUS_STARTUP,
    STATUS_THERMOMETER_FAULT,
    SYNC,
    T_US_MODULUS,
    THERMOMETER_COUNTS_PER_C,
    THERMOMETER_INVALID,
    TYPE_IDENTITY,
    TYPE_SAMPLE,
    Event,
    IdentityFrame,
    SampleFrame,
    UnknownFrame,
    crc32,
    encode_event,
    encode_frame,
    encode_identity,
    encode_sample,
    status_names,
)

__all__ = [name for name in dir() if not name.startswith("_")]
