/*
 * make_vectors.c - writes the protocol v1 golden vectors with the reference
 * encoder (hosted C99; uses stdio).
 *
 *   make_vectors GOLDEN_BIN GOLDEN_TXT   encode the fixed frame list below:
 *                                        GOLDEN_BIN gets the frames back to
 *                                        back, GOLDEN_TXT one line per frame
 *   make_vectors --crc-check             print fog_crc32_update over ASCII
 *                                        "123456789" (must be 0xcbf43926)
 *   make_vectors --crc-stdin             print the CRC of all bytes on stdin
 *
 * GOLDEN_TXT line formats (fields separated by one space, then " | " and the
 * frame's bytes as lower-case hex pairs separated by one space):
 *
 *   SAMPLE seq=U t_us=U dtheta=I t_top=I t_bottom=I t_housing=I status=0xHHHH crc=0xHHHHHHHH | aa 55 ...
 *   IDENTITY serial="S" firmware=0xHHHH rate_hz=U scale_bits=0xHHHHHHHH scale=G crc=0xHHHHHHHH | aa 55 ...
 *   FRAME type=0xHH len=U payload=HEX crc=0xHHHHHHHH | aa 55 ...
 *
 * serial is printed up to its first NUL (it never contains '"' or '\\');
 * scale_bits is the exact IEEE-754 binary32 pattern, scale the same value
 * printed with %.9g (enough digits to round-trip a binary32), for humans.
 * Lines starting with '#' are comments.
 *
 * Exit status: 0 on success, 1 on an encoder self-test failure, 2 on a usage
 * or I/O error.
 */
#include "fog_protocol.h"

#include <inttypes.h>
#include <stdio.h>
#include <string.h>

static FILE *g_bin;
static FILE *g_txt;
static int g_failed;

static void fail(const char *what)
{
    fprintf(stderr, "make_vectors: self-test failed: %s\n", what);
    g_failed = 1;
}

static uint32_t get_u32le(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* " | aa 55 ..." plus newline, and the raw bytes to the binary file. */
static void emit(const uint8_t *frame, size_t n)
{
    size_t i;
    fprintf(g_txt, " crc=0x%08" PRIx32 " |", get_u32le(frame + n - FOG_CRC_LEN));
    for (i = 0; i < n; i++) {
        fprintf(g_txt, " %02x", (unsigned)frame[i]);
    }
    fputc('\n', g_txt);
    if (fwrite(frame, 1, n, g_bin) != n) {
        fail("short write to the binary file");
    }
}

static void sample(uint16_t seq, uint32_t t_us, int32_t dtheta, int16_t t_top,
                   int16_t t_bottom, int16_t t_housing, uint16_t status)
{
    uint8_t out[FOG_SAMPLE_FRAME_LEN];
    fog_sample_t s;
    size_t n;
    s.seq = seq;
    s.t_us = t_us;
    s.dtheta = dtheta;
    s.t_top = t_top;
    s.t_bottom = t_bottom;
    s.t_housing = t_housing;
    s.status = status;
    n = fog_encode_sample(out, &s);
    if (n != FOG_SAMPLE_FRAME_LEN) {
        fail("fog_encode_sample length");
    }
    fprintf(g_txt,
            "SAMPLE seq=%u t_us=%" PRIu32 " dtheta=%" PRId32
            " t_top=%d t_bottom=%d t_housing=%d status=0x%04x",
            (unsigned)seq, t_us, dtheta, (int)t_top, (int)t_bottom, (int)t_housing,
            (unsigned)status);
    emit(out, n);
}

static void identity(const char *serial, uint16_t firmware, uint16_t rate_hz, float scale)
{
    uint8_t out[FOG_IDENTITY_FRAME_LEN];
    fog_identity_t id;
    uint32_t bits;
    size_t len = strlen(serial);
    size_t n;
    size_t i;
    if (len > FOG_SERIAL_LEN || strchr(serial, '"') != NULL || strchr(serial, '\\') != NULL) {
        fail("serial too long or not printable in the listing");
        return;
    }
    memset(id.serial, 0, sizeof id.serial); /* NUL padding */
    memcpy(id.serial, serial, len);         /* 16 characters: no NUL at all */
    id.firmware = firmware;
    id.rate_hz = rate_hz;
    id.scale = scale;
    n = fog_encode_identity(out, &id);
    if (n != FOG_IDENTITY_FRAME_LEN) {
        fail("fog_encode_identity length");
    }
    memcpy(&bits, &scale, sizeof bits);
    fprintf(g_txt, "IDENTITY serial=\"");
    for (i = 0; i < len; i++) {
        fputc(serial[i], g_txt);
    }
    fprintf(g_txt, "\" firmware=0x%04x rate_hz=%u scale_bits=0x%08" PRIx32 " scale=%.9g",
            (unsigned)firmware, (unsigned)rate_hz, bits, (double)scale);
    emit(out, n);
}

static void frame(uint8_t type, const uint8_t *payload, uint8_t len)
{
    uint8_t out[FOG_MAX_FRAME_LEN];
    size_t n = fog_encode_frame(out, sizeof out, type, payload, len);
    size_t i;
    if (n != (size_t)FOG_OVERHEAD_LEN + len) {
        fail("fog_encode_frame length");
        return;
    }
    fprintf(g_txt, "FRAME type=0x%02x len=%u payload=", (unsigned)type, (unsigned)len);
    for (i = 0; i < len; i++) {
        fprintf(g_txt, "%02x", (unsigned)payload[i]);
    }
    emit(out, n);
}

/* API edge cases that do not show up in the vectors. */
static void self_test(void)
{
    static const uint8_t check[] = "123456789";
    uint8_t buf[FOG_MAX_FRAME_LEN];
    uint8_t ref[FOG_SAMPLE_FRAME_LEN];
    fog_sample_t s;
    uint32_t c;
    size_t i;

    if (fog_crc32_update(0u, check, 9u) != FOG_CRC32_CHECK) {
        fail("CRC check value");
    }
    c = 0u;
    for (i = 0; i < 9u; i++) {
        c = fog_crc32_update(c, check + i, 1u);
    }
    if (c != FOG_CRC32_CHECK) {
        fail("incremental CRC");
    }
    if (fog_crc32_update(0u, NULL, 0u) != 0u) {
        fail("CRC of nothing is not 0");
    }
    if (fog_encode_frame(buf, FOG_OVERHEAD_LEN - 1u, 0x7Eu, NULL, 0u) != 0u) {
        fail("fog_encode_frame accepted a too small buffer");
    }
    if (fog_encode_frame(buf, FOG_OVERHEAD_LEN, 0x7Eu, NULL, 0u) != FOG_OVERHEAD_LEN) {
        fail("fog_encode_frame refused an empty payload");
    }
    if (fog_encode_frame(buf, sizeof buf, 0x7Eu, NULL, 1u) != 0u) {
        fail("fog_encode_frame accepted a NULL payload");
    }
    /* A SAMPLE through the generic framer equals fog_encode_sample. */
    memset(&s, 0, sizeof s);
    s.seq = 0x1234u;
    s.dtheta = -2;
    s.status = FOG_STATUS_STARTUP;
    fog_encode_sample(ref, &s);
    if (fog_encode_frame(buf, FOG_SAMPLE_FRAME_LEN - 1u, FOG_TYPE_SAMPLE, ref + FOG_HEADER_LEN,
                         FOG_SAMPLE_PAYLOAD_LEN) != 0u
        || fog_encode_frame(buf, FOG_SAMPLE_FRAME_LEN, FOG_TYPE_SAMPLE, ref + FOG_HEADER_LEN,
                            FOG_SAMPLE_PAYLOAD_LEN) != FOG_SAMPLE_FRAME_LEN
        || memcmp(buf, ref, FOG_SAMPLE_FRAME_LEN) != 0) {
        fail("fog_encode_frame and fog_encode_sample disagree");
    }
}

#define T_INVALID ((int16_t)FOG_THERMOMETER_INVALID)

static void write_vectors(void)
{
    /* A full SAMPLE frame (seq 7) used as the payload of an unknown frame:
       a decoder must skip it whole, never emit the inner SAMPLE. */
    uint8_t inner[FOG_SAMPLE_FRAME_LEN];
    fog_sample_t s;
    static const uint8_t unknown_payload[] = {0x01, 0x02, 0xAA, 0x55, 0x01, 0x12, 0x03};
    uint8_t max_payload[255];
    size_t i;

    fprintf(g_txt,
            "# FOG wire protocol v1 golden vectors: one line per frame of golden.bin, in order.\n"
            "# Generated by firmware_protocol/c/make_vectors.c; do not edit (make -C firmware_protocol/c vectors).\n"
            "# Format: KIND field=value ... | frame bytes in hex. Specification: firmware_protocol/PROTOCOL.md.\n");

    /* Power-up: IDENTITY first, then samples from seq 0 with the start-up bit. */
    identity("FOG-A", 0x0102u, 1000u, 0.017f); /* 0.017 not exact in binary32 */
    sample(0u, 0u, 0, 6400, 6400, 5000, FOG_STATUS_STARTUP);
    sample(1u, 1000u, 3, 6401, 6399, 5001, FOG_STATUS_STARTUP);
    /* Normal samples. */
    sample(2u, 2000u, 12, 6402, 6400, 5001, 0u);
    sample(3u, 3000u, -7, 6402, 6401, 5002, 0u);
    sample(4u, 4001u, 0, 6403, 6401, 5002, 0u);
    /* Extreme and negative dtheta. */
    sample(5u, 5000u, -1, 6403, 6402, 5003, 0u);
    sample(6u, 6000u, INT32_MIN, 6403, 6402, 5003, FOG_STATUS_OVER_RANGE);
    sample(7u, 7000u, INT32_MAX, 6404, 6402, 5003, FOG_STATUS_OVER_RANGE);
    /* Thermometer sentinel on each sensor, then on all three; extremes. */
    sample(8u, 8000u, 5, T_INVALID, 6402, 5003, FOG_STATUS_THERMOMETER_FAULT);
    sample(9u, 9000u, 5, 6404, T_INVALID, 5003, FOG_STATUS_THERMOMETER_FAULT);
    sample(10u, 10000u, 5, 6404, 6403, T_INVALID, FOG_STATUS_THERMOMETER_FAULT);
    sample(11u, 11000u, 4, T_INVALID, T_INVALID, T_INVALID, FOG_STATUS_THERMOMETER_FAULT);
    sample(12u, 12000u, 4, -32767, 32767, -1, 0u);
    sample(13u, 13000u, 4, 32767, -32767, 0, 0u);
    /* IDENTITY once per second, between SAMPLE frames: seq does not advance. */
    identity("FOG-A", 0x0102u, 1000u, 0.017f);
    /* Every status bit alone, a reserved bit, all bits. */
    sample(14u, 14000u, 2, 6405, 6403, 5004, FOG_STATUS_LIGHT_SOURCE_FAULT);
    sample(15u, 15000u, 2, 6405, 6403, 5004, FOG_STATUS_LOOP_UNLOCKED);
    sample(16u, 16000u, 2, 6405, 6403, 5004, FOG_STATUS_THERMOMETER_FAULT);
    sample(17u, 17000u, 2, 6405, 6403, 5004, FOG_STATUS_OVER_RANGE);
    sample(18u, 18000u, 2, 6405, 6403, 5004, FOG_STATUS_STARTUP);
    sample(19u, 19000u, 2, 6405, 6403, 5004, 0x0020u); /* reserved bit 5 */
    sample(20u, 20000u, 2, 6405, 6403, 5004, 0x8000u); /* reserved bit 15 */
    sample(21u, 21000u, 2, 6405, 6403, 5004, 0xFFFFu);
    /* False sync inside payloads: seq 0x55AA is sent as "aa 55"; t_us as
       "aa 55 aa 55"; dtheta 0x120155AA as "aa 55 01 12", a SAMPLE header. */
    sample(0x55AAu, 0x55AA55AAul, 0x120155AAl, 6405, 6403, 5004, 0u);
    /* dtheta -2141869568 = 0x8055AA00: "00 aa 55 80"; t_top 0x55AA; status 0x55AA. */
    sample(0x55ABu, 0x55AA59CAul, -2141869568l, 0x55AA, -21846, 5004, 0x55AAu);
    /* seq wraps 65535 -> 0 (after a gap from 0x55AB). */
    sample(65533u, 100000000ul, 1, 6406, 6404, 5005, 0u);
    sample(65534u, 100001000ul, 1, 6406, 6404, 5005, 0u);
    sample(65535u, 100002000ul, 1, 6406, 6404, 5005, 0u);
    sample(0u, 100003000ul, 1, 6406, 6404, 5005, 0u);
    sample(1u, 100004000ul, 1, 6406, 6404, 5005, 0u);
    /* t_us wraps near 2^32. */
    sample(2u, 4294965296ul, -5, 6407, 6405, 5006, 0u);
    sample(3u, 4294966296ul, -5, 6407, 6405, 5006, 0u);
    sample(4u, 4294967295ul, -5, 6407, 6405, 5006, 0u);
    sample(5u, 999u, -5, 6407, 6405, 5006, 0u);
    sample(6u, 1999u, -5, 6407, 6405, 5006, 0u);
    /* Other instruments: a full 16-character serial (no NUL), a short one,
       other rates, firmware versions and scale factors. */
    identity("FOG2-SN-00012345", 0x0102u, 100u, 0.1f);    /* 0.1: not exact */
    identity("X", 0x0203u, 1000u, 1.0f);
    identity("FOG-B7", 0x0102u, 100u, 0.0625f);            /* exact */
    identity("FOG-C", 0xFFFFu, 2000u, 3.0517578125e-05f);  /* 2^-15, exact */
    identity("", 0x0000u, 0u, 1.2345678e-3f);             /* empty serial */
    /* Unknown types: skipped and counted, never decoded. */
    frame(0x7Eu, unknown_payload, (uint8_t)sizeof unknown_payload);
    frame(0x7Eu, NULL, 0u);
    memset(&s, 0, sizeof s);
    s.seq = 7u;
    s.t_us = 7000u;
    s.dtheta = 1;
    s.status = FOG_STATUS_STARTUP;
    fog_encode_sample(inner, &s);
    frame(0x03u, inner, (uint8_t)sizeof inner); /* a whole valid SAMPLE frame inside */
    for (i = 0; i < sizeof max_payload; i++) {
        max_payload[i] = (uint8_t)(i ^ 0xAAu);
    }
    max_payload[100] = 0xAAu;
    max_payload[101] = 0x55u;
    frame(0xFFu, max_payload, (uint8_t)sizeof max_payload); /* longest frame, 263 bytes */
    /* Back to samples after the unknown frames. */
    sample(7u, 2999u, 6, 6408, 6406, 5007, 0u);
    identity("FOG-A", 0x0102u, 1000u, 0.017f);
    sample(8u, 3999u, -6, 6408, 6406, 5007, 0u);
}

int main(int argc, char **argv)
{
    if (argc == 2 && strcmp(argv[1], "--crc-check") == 0) {
        static const uint8_t check[] = "123456789";
        self_test();
        printf("0x%08" PRIx32 "\n", fog_crc32_update(0u, check, 9u));
        return g_failed ? 1 : 0;
    }
    if (argc == 2 && strcmp(argv[1], "--crc-stdin") == 0) {
        uint8_t buf[4096];
        uint32_t c = 0u;
        size_t n;
        while ((n = fread(buf, 1, sizeof buf, stdin)) > 0u) {
            c = fog_crc32_update(c, buf, n);
        }
        if (ferror(stdin)) {
            fprintf(stderr, "make_vectors: read error on stdin\n");
            return 2;
        }
        printf("0x%08" PRIx32 "\n", c);
        return 0;
    }
    if (argc != 3 || argv[1][0] == '-') {
        fprintf(stderr,
                "usage: %s GOLDEN_BIN GOLDEN_TXT\n"
                "       %s --crc-check | --crc-stdin\n",
                argv[0], argv[0]);
        return 2;
    }
    self_test();
    g_bin = fopen(argv[1], "wb");
    g_txt = fopen(argv[2], "w");
    if (g_bin == NULL || g_txt == NULL) {
        fprintf(stderr, "make_vectors: cannot open the output files\n");
        return 2;
    }
    write_vectors();
    if (fclose(g_bin) != 0 || fclose(g_txt) != 0) {
        fprintf(stderr, "make_vectors: error writing the output files\n");
        return 2;
    }
    return g_failed ? 1 : 0;
}
