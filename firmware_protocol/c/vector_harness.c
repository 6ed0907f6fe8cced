/* vector_harness.c: drives the generated codec from text on stdin, so that
 * tests/unit/test_c_codec.py can compare C and Python on the shared vectors.
 *
 * Hand-written (not generated); host-only test code, never linked into firmware.
 * It goes through the by-id API, which calls the per-message encoders and decoders,
 * so one harness serves every message the DBC defines.
 *
 * One command per line, one answer line per command:
 *   E <frame_id> <counter> <v1> ... <vn>  ->  OK <hex bytes>             | ERR <name>
 *   D <frame_id> <hex bytes>              ->  OK <counter> <v1> ... <vn> | ERR <name>
 *   C <hex bytes>                         ->  OK <crc8, decimal>
 * frame_id and counter are C integer literals (decimal or 0x...); values are read with
 * strtod (so "nan" and "inf" work) and printed with %.17g, which round-trips a double.
 * A line the harness cannot parse gets "BAD <reason>" and makes the exit status 2.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "handctl_protocol.h"

#define MAX_LINE 4096
#define MAX_BYTES 64
#define MAX_VALUES 32

static const char *error_name(int rc)
{
    switch (rc) {
    case HANDCTL_ERR_ARG:
        return "ARG";
    case HANDCTL_ERR_LENGTH:
        return "LENGTH";
    case HANDCTL_ERR_CRC:
        return "CRC";
    case HANDCTL_ERR_RANGE:
        return "RANGE";
    case HANDCTL_ERR_ID:
        return "ID";
    default:
        return "UNKNOWN";
    }
}

static int parse_ulong(const char *text, unsigned long max, unsigned long *value)
{
    char *end;
    if (text == NULL) {
        return 0;
    }
    *value = strtoul(text, &end, 0);
    return *end == '\0' && end != text && *value <= max;
}

static int hex_digit(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

/* Returns the number of bytes, or -1 for text that is not whole hex bytes. */
static int parse_hex(const char *text, uint8_t *bytes, size_t capacity)
{
    size_t n = 0u;
    if (text == NULL) {
        return 0; /* no bytes at all */
    }
    while (text[0] != '\0') {
        int hi = hex_digit(text[0]);
        int lo = hi < 0 ? -1 : hex_digit(text[1]);
        if (lo < 0 || n == capacity) {
            return -1;
        }
        bytes[n++] = (uint8_t)(hi * 16 + lo);
        text += 2;
    }
    return (int)n;
}

static void print_hex(const uint8_t *bytes, size_t n)
{
    size_t i;
    for (i = 0u; i < n; ++i) {
        printf("%02x", bytes[i]);
    }
}

static int do_encode(void)
{
    unsigned long frame_id;
    unsigned long counter;
    double values[MAX_VALUES];
    size_t n = 0u;
    uint8_t frame[HANDCTL_MAX_LENGTH];
    const char *tok;
    int rc;
    int length;

    if (!parse_ulong(strtok(NULL, " \t\r\n"), 0x1FFFFFFFul, &frame_id)
            || !parse_ulong(strtok(NULL, " \t\r\n"), 255ul, &counter)) {
        printf("BAD expected E <frame_id> <counter> <values...>\n");
        return 0;
    }
    while ((tok = strtok(NULL, " \t\r\n")) != NULL) {
        char *end;
        if (n == MAX_VALUES) {
            printf("BAD too many values\n");
            return 0;
        }
        values[n] = strtod(tok, &end);
        if (*end != '\0' || end == tok) {
            printf("BAD not a number: %s\n", tok);
            return 0;
        }
        ++n;
    }
    rc = handctl_encode_by_id((uint32_t)frame_id, frame, sizeof frame, (uint8_t)counter,
                              values, n);
    if (rc != HANDCTL_OK) {
        printf("ERR %s\n", error_name(rc));
        return 1;
    }
    length = handctl_frame_length((uint32_t)frame_id);
    printf("OK ");
    print_hex(frame, (size_t)length);
    printf("\n");
    return 1;
}

static int do_decode(void)
{
    unsigned long frame_id;
    uint8_t frame[MAX_BYTES];
    double values[HANDCTL_MAX_SIGNALS];
    uint8_t counter = 0u;
    int n_bytes;
    int n_values;
    int rc;
    int i;

    if (!parse_ulong(strtok(NULL, " \t\r\n"), 0x1FFFFFFFul, &frame_id)) {
        printf("BAD expected D <frame_id> <hex>\n");
        return 0;
    }
    n_bytes = parse_hex(strtok(NULL, " \t\r\n"), frame, sizeof frame);
    if (n_bytes < 0 || strtok(NULL, " \t\r\n") != NULL) {
        printf("BAD expected one string of hex bytes (at most %d)\n", MAX_BYTES);
        return 0;
    }
    rc = handctl_decode_by_id((uint32_t)frame_id, frame, (size_t)n_bytes, &counter, values,
                              HANDCTL_MAX_SIGNALS);
    if (rc != HANDCTL_OK) {
        printf("ERR %s\n", error_name(rc));
        return 1;
    }
    n_values = handctl_signal_count((uint32_t)frame_id);
    printf("OK %u", (unsigned)counter);
    for (i = 0; i < n_values; ++i) {
        printf(" %.17g", values[i]);
    }
    printf("\n");
    return 1;
}

static int do_crc(void)
{
    uint8_t bytes[MAX_BYTES];
    int n = parse_hex(strtok(NULL, " \t\r\n"), bytes, sizeof bytes);
    if (n < 0) {
        printf("BAD expected C <hex>\n");
        return 0;
    }
    printf("OK %u\n", (unsigned)handctl_crc8(bytes, (size_t)n));
    return 1;
}

int main(void)
{
    char line[MAX_LINE];
    int status = 0;

    while (fgets(line, sizeof line, stdin) != NULL) {
        const char *cmd = strtok(line, " \t\r\n");
        int ok;
        if (cmd == NULL) {
            continue;
        }
        if (strcmp(cmd, "E") == 0) {
            ok = do_encode();
        } else if (strcmp(cmd, "D") == 0) {
            ok = do_decode();
        } else if (strcmp(cmd, "C") == 0) {
            ok = do_crc();
        } else {
            printf("BAD unknown command %s\n", cmd);
            ok = 0;
        }
        if (!ok) {
            status = 2;
        }
    }
    return status;
}
