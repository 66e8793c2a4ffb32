#include "slcan.h"

#include <string.h>

#define RING_MASK (SLCAN_RING_BYTES - 1u)
#define OK_REPLY '\r'
#define ERROR_REPLY '\a'

static const char HEX[] = "0123456789ABCDEF";

void slcan_init(slcan_rx *rx)
{
    (void)memset(rx, 0, sizeof *rx);
}

void slcan_rx_push(slcan_rx *rx, uint8_t byte)
{
    uint32_t head = rx->head;
    if (head - rx->tail >= SLCAN_RING_BYTES) {
        rx->overflows += 1u;
        if (!rx->lost) { /* the line that reaches this point lost bytes: remember where */
            rx->lost_at = head;
            rx->lost = true;
        }
        return;
    }
    rx->ring[head & RING_MASK] = byte;
    rx->head = head + 1u;
}

static int hex_value(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    return -1;
}

bool slcan_decode(const char *line, uint32_t len, can_frame_t *frame)
{
    if (len < 5u || line[0] != 't') {
        return false;
    }
    uint32_t id = 0u;
    for (uint32_t i = 1u; i <= 3u; ++i) {
        int v = hex_value(line[i]);
        if (v < 0) {
            return false;
        }
        id = (id << 4) | (uint32_t)v;
    }
    int dlc = hex_value(line[4]);
    if (dlc < 0 || dlc > 8 || id > 0x7FFu || len != 5u + 2u * (uint32_t)dlc) {
        return false;
    }
    frame->id = id;
    frame->len = (uint8_t)dlc;
    for (uint32_t i = 0u; i < (uint32_t)dlc; ++i) {
        int hi = hex_value(line[5u + 2u * i]);
        int lo = hex_value(line[6u + 2u * i]);
        if (hi < 0 || lo < 0) {
            return false;
        }
        frame->data[i] = (uint8_t)((hi << 4) | lo);
    }
    return true;
}

uint32_t slcan_encode(const can_frame_t *frame, char *out)
{
    if (frame->id > 0x7FFu || frame->len > 8u) {
        return 0u;
    }
    uint32_t n = 0u;
    out[n++] = 't';
    out[n++] = HEX[(frame->id >> 8) & 0xFu];
    out[n++] = HEX[(frame->id >> 4) & 0xFu];
    out[n++] = HEX[frame->id & 0xFu];
    out[n++] = HEX[frame->len];
    for (uint32_t i = 0u; i < frame->len; ++i) {
        out[n++] = HEX[frame->data[i] >> 4];
        out[n++] = HEX[frame->data[i] & 0xFu];
    }
    out[n++] = '\r';
    return n;
}

/* A command line: its answer. 'O' and 'L' open the channel, 'C' closes it; bit rates, version, serial
 * number, status flags and time stamps are accepted and ignored (the emulated bus has no bit timing). */
static uint8_t command(slcan_rx *rx, const char *line, uint32_t len)
{
    switch (line[0]) {
    case 'O':
    case 'L':
        rx->open = true;
        return OK_REPLY;
    case 'C':
        rx->open = false;
        return OK_REPLY;
    case 'S':
    case 's':
    case 'V':
    case 'v':
    case 'N':
    case 'F':
    case 'Z':
        return len <= 12u ? OK_REPLY : ERROR_REPLY;
    default:
        rx->bad_lines += 1u;
        return ERROR_REPLY;
    }
}

#define TIME_DIGITS_MAX 8u

/* A time line ("Y" and 1-8 hex digits): its advance into *us; false if malformed. */
static bool parse_time(const char *line, uint32_t len, uint32_t *us)
{
    bool ok = (len >= 2u) && (len <= (1u + TIME_DIGITS_MAX));
    uint32_t value = 0u;
    for (uint32_t i = 1u; ok && (i < len); ++i) {
        int v = hex_value(line[i]);
        ok = (v >= 0);
        value = (value << 4) | (uint32_t)(ok ? v : 0);
    }
    if (ok) {
        *us = value;
    }
    return ok;
}

slcan_event slcan_rx_poll(slcan_rx *rx, can_frame_t *frame, uint8_t *reply)
{
    for (uint32_t budget = 0u; budget <= SLCAN_RING_BYTES; ++budget) {
        if (rx->lost && rx->tail == rx->lost_at) { /* bytes were dropped here: this line lost some */
            rx->line_broken = true;
            rx->lost = false;
        }
        if (rx->tail == rx->head) {
            break;
        }
        char c = (char)rx->ring[rx->tail & RING_MASK];
        rx->tail += 1u;
        if (c != '\r' && c != '\n') {
            if (rx->line_len < SLCAN_MAX_LINE) {
                rx->line[rx->line_len++] = c;
            } else {
                rx->line_broken = true;
            }
            continue;
        }
        uint32_t len = rx->line_len;
        bool broken = rx->line_broken;
        rx->line_len = 0u;
        rx->line_broken = false;
        if (len == 0u) {
            continue; /* an empty line (a "\r\n" pair, or a bare terminator) */
        }
        if (broken) {
            rx->bad_lines += 1u;
            *reply = ERROR_REPLY;
            return SLCAN_REPLY;
        }
        if (rx->line[0] == 't') {
            if (slcan_decode(rx->line, len, frame) && rx->open) {
                return SLCAN_FRAME;
            }
            rx->bad_lines += 1u;
            *reply = ERROR_REPLY;
            return SLCAN_REPLY;
        }
        if (rx->line[0] == 'Y') {
            bool ok = parse_time(rx->line, len, &rx->advance_us);
            rx->bad_lines += ok ? 0u : 1u;
            *reply = ERROR_REPLY; /* the answer if refused; a taken line is answered by the transport */
            return ok ? SLCAN_TIME : SLCAN_REPLY;
        }
        *reply = command(rx, rx->line, len);
        return SLCAN_REPLY;
    }
    return SLCAN_NONE;
}
