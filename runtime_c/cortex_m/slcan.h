/*
 * Serial CAN framing (SLCAN, the Lawicel ASCII protocol of serial CAN adapters), the firmware node's side.
 *
 * A classic standard-ID data frame travels as one line: 't', 3 hex digits of ID, the length digit 0-8,
 * two hex digits per data byte, '\r' ("t1234AABBCCDD\r"). The receiver also answers the adapter
 * commands a host sends on opening (O, C, S0-S8, L, V, N, F, Z): '\r' for done, '\a' (BEL) for refused,
 * as python-can's `slcan` interface and can-utils' `slcand` expect. Extended IDs, remote and CAN FD
 * frames are refused ('\a') and counted: the policy's database has none.
 *
 * One line beyond Lawicel's, for processor-in-the-loop runs: 'Y' and 1-8 hex digits, "the simulation's
 * time advanced by this many microseconds" (SLCAN_TIME). The firmware's simulated clock (clock_sim.c)
 * takes it; the transport answers "Y\r" once the node has acted on the new time (transport_uart.c).
 *
 * Bytes arrive through slcan_rx_push (from the UART's receive interrupt) into a ring buffer; a full
 * buffer drops the byte and counts it (the line it belonged to is then corrupt and dropped too).
 * No malloc; every loop is bounded by SLCAN_MAX_LINE or SLCAN_RING_BYTES.
 */
#ifndef EMBEDRL_SLCAN_H
#define EMBEDRL_SLCAN_H

#include <stdbool.h>
#include <stdint.h>

#include "platform.h"

#define SLCAN_RING_BYTES 512u /* power of two: eight observation frames of 22 bytes fit twice over */
#define SLCAN_MAX_LINE 32u    /* "T" + 8 + 1 + 16 + "\r" is the longest line a classic frame needs */
#define SLCAN_FRAME_LINE 22u  /* bytes of a standard 8-byte frame's line, terminator included */

typedef enum {
    SLCAN_NONE = 0,  /* no complete line yet */
    SLCAN_FRAME = 1, /* *frame holds a standard-ID data frame */
    SLCAN_REPLY = 2, /* a command: *reply is the byte to answer with ('\r' or '\a') */
    SLCAN_TIME = 3,  /* a time line: rx->advance_us holds the microseconds it advances the clock by */
} slcan_event;

typedef struct {
    uint8_t ring[SLCAN_RING_BYTES];
    volatile uint32_t head; /* written by the receive interrupt only */
    volatile uint32_t tail; /* written by the main loop only */
    volatile uint32_t overflows; /* bytes dropped because the ring was full */
    volatile uint32_t lost_at;   /* ring position at which bytes were dropped (valid while lost) */
    volatile bool lost;
    char line[SLCAN_MAX_LINE];
    uint32_t line_len;
    bool line_broken; /* too long, or bytes of it were dropped: discarded at its terminator */
    uint32_t bad_lines;  /* lines that were neither a valid frame nor a known command */
    bool open;           /* after 'O' (or 'L'): frames are passed on */
    uint32_t advance_us; /* the last time line's advance (valid after SLCAN_TIME) */
} slcan_rx;

void slcan_init(slcan_rx *rx);

/* One received byte (interrupt context): into the ring, or counted as an overflow. */
void slcan_rx_push(slcan_rx *rx, uint8_t byte);

/* Take bytes from the ring until a line is complete: SLCAN_NONE when the ring is empty first. */
slcan_event slcan_rx_poll(slcan_rx *rx, can_frame_t *frame, uint8_t *reply);

/* The line for a classic standard-ID frame (len <= 8), terminator included, into out (at least
 * SLCAN_MAX_LINE bytes); returns its length, 0 if the frame cannot travel as SLCAN. */
uint32_t slcan_encode(const can_frame_t *frame, char *out);

/* Parse one line (without its terminator) as a standard-ID data frame: true on success. */
bool slcan_decode(const char *line, uint32_t len, can_frame_t *frame);

#endif /* EMBEDRL_SLCAN_H */
