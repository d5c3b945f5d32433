/*
 * fog_protocol.h - reference encoder for the FOG instrument wire protocol v1.
 *
 * C99, freestanding-friendly: no dynamic allocation, no stdio, no dependence
 * on host endianness or struct layout (every multi-byte field is written
 * byte by byte, little-endian).  The only library calls are memcpy (to read
 * the bit pattern of the f32 scale factor) and nothing else.
 *
 * Frame:  AA 55 | type u8 | len u8 | payload[len] | crc32 u32 LE
 * CRC-32/ISO-HDLC over type, len and payload.
 *
 * See ../PROTOCOL.md, the protocol's specification.
 */
#ifndef FOG_PROTOCOL_H
#define FOG_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- framing ------------------------------------------------------------ */
#define FOG_SYNC0 0xAAu
#define FOG_SYNC1 0x55u
#define FOG_HEADER_LEN 4u   /* sync(2) + type(1) + len(1) */
#define FOG_CRC_LEN 4u
#define FOG_OVERHEAD_LEN (FOG_HEADER_LEN + FOG_CRC_LEN) /* 8 */
#define FOG_MAX_PAYLOAD_LEN 255u
#define FOG_MAX_FRAME_LEN (FOG_OVERHEAD_LEN + FOG_MAX_PAYLOAD_LEN) /* 263 */

/* ---- frame types -------------------------------------------------------- */
#define FOG_TYPE_SAMPLE 0x01u
#define FOG_TYPE_IDENTITY 0x02u

/* ---- lengths ------------------------------------------------------------ */
#define FOG_SAMPLE_PAYLOAD_LEN 18u
#define FOG_IDENTITY_PAYLOAD_LEN 24u
#define FOG_SAMPLE_FRAME_LEN (FOG_OVERHEAD_LEN + FOG_SAMPLE_PAYLOAD_LEN)     /* 26 */
#define FOG_IDENTITY_FRAME_LEN (FOG_OVERHEAD_LEN + FOG_IDENTITY_PAYLOAD_LEN) /* 32 */
#define FOG_SERIAL_LEN 16u

/* ---- SAMPLE status bits (bits 5..15 reserved: sent as given) ------------ */
#define FOG_STATUS_LIGHT_SOURCE_FAULT 0x0001u
#define FOG_STATUS_LOOP_UNLOCKED 0x0002u
#define FOG_STATUS_THERMOMETER_FAULT 0x0004u
#define FOG_STATUS_OVER_RANGE 0x0008u
#define FOG_STATUS_STARTUP 0x0010u
#define FOG_STATUS_RESERVED_MASK 0xFFE0u

/* Thermometer value meaning "no valid reading" (0x8000). */
#define FOG_THERMOMETER_INVALID (-32767 - 1)
/* Thermometer resolution: 1/256 degC per count. */
#define FOG_THERMOMETER_COUNTS_PER_C 256

/* CRC-32/ISO-HDLC parameters. */
#define FOG_CRC32_INIT 0xFFFFFFFFul
#define FOG_CRC32_XOROUT 0xFFFFFFFFul
#define FOG_CRC32_POLY_REFLECTED 0xEDB88320ul /* 0x04C11DB7 bit-reversed */
#define FOG_CRC32_CHECK 0xCBF43926ul          /* CRC of ASCII "123456789" */

/* One SAMPLE frame's fields, wire values (no scaling). */
typedef struct {
    uint16_t seq;       /* +1 per SAMPLE frame, wraps at 65536 */
    uint32_t t_us;      /* instrument clock, microseconds, wraps at 2^32 */
    int32_t dtheta;     /* angle increment since the previous SAMPLE, counts */
    int16_t t_top;      /* 1/256 degC, FOG_THERMOMETER_INVALID = no reading */
    int16_t t_bottom;
    int16_t t_housing;
    uint16_t status;    /* FOG_STATUS_* bits */
} fog_sample_t;

/* One IDENTITY frame's fields. */
typedef struct {
    /* ASCII, NUL-padded.  All 16 bytes are sent as they are; a 16-character
       serial has no terminating NUL.  Bytes after the first NUL should be 0. */
    char serial[FOG_SERIAL_LEN];
    uint16_t firmware;  /* (major << 8) + minor */
    uint16_t rate_hz;   /* nominal SAMPLE rate */
    float scale;        /* arcsec per count, IEEE-754 binary32 */
} fog_identity_t;

/*
 * CRC-32/ISO-HDLC, incremental.  Start with crc = 0, feed any number of
 * chunks, the return value after the last chunk is the final CRC:
 *
 *     uint32_t c = fog_crc32_update(0, a, na);
 *     c = fog_crc32_update(c, b, nb);      // == CRC of a||b
 *
 * (the init and xorout 0xFFFFFFFF are applied inside, like zlib's crc32()).
 * Table-driven, one const 256-entry table (1 KiB, in flash on most MCUs).
 */
uint32_t fog_crc32_update(uint32_t crc, const uint8_t *p, size_t n);

/*
 * Frame an arbitrary payload: writes 8 + len bytes to out and returns that
 * count, or 0 (writing nothing) when out_cap is too small or out is NULL or
 * payload is NULL with len > 0.  payload may be NULL when len == 0.  payload
 * must not overlap out.
 */
size_t fog_encode_frame(uint8_t *out, size_t out_cap, uint8_t type,
                        const uint8_t *payload, uint8_t len);

/* Encode one SAMPLE frame; writes and returns FOG_SAMPLE_FRAME_LEN (26). */
size_t fog_encode_sample(uint8_t out[FOG_SAMPLE_FRAME_LEN], const fog_sample_t *s);

/* Encode one IDENTITY frame; writes and returns FOG_IDENTITY_FRAME_LEN (32). */
size_t fog_encode_identity(uint8_t out[FOG_IDENTITY_FRAME_LEN], const fog_identity_t *id);

#ifdef __cplusplus
}
#endif

#endif /* FOG_PROTOCOL_H */
