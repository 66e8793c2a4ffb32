/*
 * libFuzzer harness of the node's receive path (make -C runtime_c fuzz): any sequence of frames, clock
 * steps, bus-state changes and link losses, on the fake transport and clock, under ASan and UBSan.
 *
 * Input: records of RECORD_BYTES bytes: [kind][a][b][8 payload bytes].
 *   kind % 4 == 0  a frame: ID = first observation ID - 1 + a % (frames + 2) (so neighbours too),
 *                  length b % 10, the payload;
 *   kind % 4 == 1  the clock advances by a | b << 8 ms (mod 4096), then node_poll;
 *   kind % 4 == 2  an error frame's bus state, a % 3;
 *   kind % 4 == 3  the link is lost (a odd) or restored (a even).
 *
 * Invariants (abort on violation, which libFuzzer reports as a crash):
 *   1. an action answering a frame carries a Step for which every observation frame with a good CRC and
 *      length has arrived: never an action from frames of two steps or from a partial observation;
 *   2. an action sent while the node is SAFE is the safe action;
 *   3. the watchdog: after node_poll, an armed node in RUN has had a valid observation within the timeout.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "e2e.h"
#include "fake_platform.h"
#include "node.h"
#include "policy_dbc.h"
#include "policy_io.h"

#define RECORD_BYTES 11u
#define TIMEOUT_MS 100u
#define MAX_RECORDS 4096u

static const node_config config = {TIMEOUT_MS, 3u, 1000u, 0u};
static uint32_t arrived[POLICY_IO_STEP_MODULO]; /* per Step: bit k = a good frame of part k arrived */

static void check(int ok)
{
    if (!ok) {
        abort();
    }
}

static void decode_action(const can_frame_t *f, float act[2], uint16_t *step)
{
    struct policy_dbc_action_t m;
    check(policy_dbc_action_unpack(&m, f->data, 8) == 0);
    act[0] = (float)policy_dbc_action_force_left_decode(m.force_left);
    act[1] = (float)policy_dbc_action_force_right_decode(m.force_right);
    *step = m.step;
}

/* Invariants 1 and 2 over the frames the node sent during one call. */
static void check_sent(const node_t *node, int answering)
{
    static const float safe[POLICY_ACT_DIM] = POLICY_SAFE_ACTION;
    const uint32_t all = (uint32_t)((1ull << POLICY_IO_OBS_FRAMES) - 1u);
    for (unsigned i = 0; i < fake_sent_count(); ++i) {
        const can_frame_t *f = fake_sent(i);
        if (f->id != POLICY_DBC_ACTION_FRAME_ID) {
            continue;
        }
        check(e2e_crc_ok(f->id, f->data, f->len));
        float act[2];
        uint16_t step;
        decode_action(f, act, &step);
        if (answering) {
            check((arrived[step % POLICY_IO_STEP_MODULO] & all) == all);
        }
        if (node->state == NODE_SAFE) {
            for (unsigned k = 0; k < 2u; ++k) { /* within the signal's quantisation */
                float d = act[k] - safe[k];
                check(d < 4e-6f && d > -4e-6f);
            }
        }
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    node_t node;
    uint32_t now = 1000u;
    memset(arrived, 0, sizeof arrived);
    fake_reset();
    fake_fail_sends(false);
    fake_set_ms(now);
    node_init(&node, &config, now);
    size_t records = size / RECORD_BYTES;
    if (records > MAX_RECORDS) {
        records = MAX_RECORDS;
    }
    for (size_t r = 0; r < records; ++r) {
        const uint8_t *rec = data + r * RECORD_BYTES;
        fake_reset();
        switch (rec[0] % 4u) {
        case 0: {
            can_frame_t frame;
            memset(&frame, 0, sizeof frame);
            frame.id = POLICY_IO_OBS_FIRST_ID - 1u + rec[1] % (POLICY_IO_OBS_FRAMES + 2u);
            frame.len = (uint8_t)(rec[2] % 10u);
            memcpy(frame.data, rec + 3, 8);
            unsigned part = frame.id - POLICY_IO_OBS_FIRST_ID;
            if (part < POLICY_IO_OBS_FRAMES && frame.len == POLICY_IO_FRAME_BYTES &&
                e2e_crc_ok(frame.id, frame.data, frame.len)) {
                float scratch[POLICY_OBS_DIM];
                uint16_t step = 0;
                uint8_t counter = 0;
                (void)policy_io_decode_observation(part, frame.data, scratch, &step, &counter);
                arrived[step % POLICY_IO_STEP_MODULO] |= 1u << part;
            }
            node_on_frame(&node, &frame, now);
            check_sent(&node, 1);
            break;
        }
        case 1:
            now += (uint32_t)(rec[1] | rec[2] << 8) % 4096u;
            fake_set_ms(now);
            (void)node_poll(&node, now);
            check_sent(&node, 0);
            check(!(node.armed && node.state == NODE_RUN) || now - node.last_valid_ms < TIMEOUT_MS);
            break;
        case 2:
            node_on_bus_state(&node, (node_bus_state)(rec[1] % 3u));
            break;
        default:
            if (rec[1] & 1u) {
                fake_fail_sends(true);
                node_link_lost(&node, now);
            } else {
                fake_fail_sends(false);
                node_link_restored(&node, now);
                check_sent(&node, 0);
            }
            break;
        }
    }
    return 0;
}
