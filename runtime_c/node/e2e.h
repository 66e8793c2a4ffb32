/*
 * End-to-end protection of CAN frames, AUTOSAR profile 1 style (see hil/policy.dbc):
 * byte 0 is a CRC-8 SAE J1850 (poly 0x1D, init 0xFF, final XOR 0xFF) over the data ID (the CAN ID,
 * low byte then high byte) and bytes 1..7; a 4-bit alive counter per message detects repeated,
 * lost and out-of-order frames.
 */
#ifndef EMBEDRL_E2E_H
#define EMBEDRL_E2E_H

#include <stdbool.h>
#include <stdint.h>

#define E2E_FRAME_BYTES 8u   /* classic CAN; a CAN FD frame protects all of its len bytes */
#define E2E_MAX_FRAME_BYTES 64u
/* E2E_CRC8_POLY, E2E_CRC8_INIT, E2E_CRC8_XOR_OUT, E2E_COUNTER_MODULO, E2E_MAX_FORWARD_JUMP (larger "forward"
 * deltas are old frames), E2E_RESYNC_FRAMES (consecutive counters that re-establish a lost sequence):
 * generated from the simulator's side (hil/e2e.py) beside the CAN codec. */
#include "e2e_params.h"

typedef enum {
    E2E_OK = 0,
    E2E_OK_SOME_LOST, /* accepted: the counter jumped forward, frames before it were lost */
    E2E_OK_RESYNC,    /* accepted: a new sequence (loss burst, sender restart) confirmed by its 2nd frame */
    E2E_BAD_CRC,
    E2E_REPEATED,
    E2E_WRONG_SEQUENCE
} e2e_status;

/* Receiver state of one message: the last accepted alive counter, and the run of consecutive
 * counters seen outside the accepted window (a candidate new sequence). */
typedef struct {
    uint8_t last_counter;
    bool seen;
    uint8_t candidate;
    uint8_t candidate_run;
} e2e_receiver;

/* CRC over the data ID and bytes 1 .. len - 1 (len 8 for classic CAN, up to 64 for CAN FD). */
uint8_t e2e_crc8(uint32_t data_id, const uint8_t *data, unsigned len);

/* Write the CRC into byte 0 (the counter must already be packed). */
void e2e_protect(uint32_t data_id, uint8_t *data, unsigned len);

bool e2e_crc_ok(uint32_t data_id, const uint8_t *data, unsigned len);

/* Check the alive counter of a frame whose CRC is good. Accepts the first frame and every frame
 * whose counter is one more than the last accepted one; a forward jump of up to
 * E2E_MAX_FORWARD_JUMP is accepted as E2E_OK_SOME_LOST (frames before it were lost). A repeated
 * counter (E2E_REPEATED) is rejected. An older one (E2E_WRONG_SEQUENCE) is rejected too, but
 * remembered: when E2E_RESYNC_FRAMES frames with consecutive counters arrive outside the window, the
 * last of them is accepted as E2E_OK_RESYNC and the sequence continues from it (after a burst of
 * lost frames or a sender restart, as AUTOSAR's E2E state machine re-synchronises). */
e2e_status e2e_check_counter(e2e_receiver *rx, uint8_t counter);

#endif /* EMBEDRL_E2E_H */
