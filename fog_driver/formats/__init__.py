"""Frame formats other than protocol v1: sans-IO decoders of commercial FOG and FOG-IMU streams.

Each format is one module with a streaming decoder in the style of ``fog_driver.protocol.FrameDecoder``
(``feed(bytes) -> events``, ``close()``, ``counters``; never raises on data, never hangs, 1-byte resync,
exact byte accounting) whose sample events are ``common.ImuSample``.  The registry that makes protocol v1
one entry among these (``--format``, sniffing, the sample stream) comes next; until then
these decoders are used directly.
"""
