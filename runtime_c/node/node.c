#include "node.h"

#include <string.h>

#include "policy_dbc.h"

#define U8_MAX 255u
#define U16_MAX 65535u
#define INFERENCE_US_MAX 1023u

/* The generated CAN glue and the generated policy must describe the same vectors. */
typedef char node_obs_dims_agree[(POLICY_IO_OBS_DIM == POLICY_OBS_DIM) ? 1 : -1];
typedef char node_act_dims_agree[(POLICY_IO_ACT_DIM == POLICY_ACT_DIM) ? 1 : -1];
typedef char node_frames_fit[(POLICY_IO_OBS_FRAMES <= 32u) ? 1 : -1];

static const float safe_action[POLICY_ACT_DIM] = POLICY_SAFE_ACTION;

static uint32_t saturate(uint32_t value, uint32_t max)
{
    return value > max ? max : value;
}

void node_init(node_t *node, const node_config *config, uint32_t now_ms)
{
    memset(node, 0, sizeof *node);
    node->config = *config;
    node->state = NODE_RUN;
    node->last_valid_ms = now_ms;
    node->last_safe_ms = now_ms;
    node->next_status_ms = now_ms;
}

static void send_action(node_t *node, const float act[POLICY_ACT_DIM], uint16_t step)
{
    for (unsigned part = 0; part < POLICY_IO_ACT_FRAMES; ++part) {
        can_frame_t frame = {POLICY_IO_ACT_FIRST_ID + part, POLICY_IO_FRAME_BYTES, {0}};
        node->saturations += policy_io_encode_action(part, act, step, node->action_counter[part], frame.data);
        e2e_protect(frame.id, frame.data);
        node->action_counter[part] = (uint8_t)((node->action_counter[part] + 1u) % E2E_COUNTER_MODULO);
        (void)transport_send(&frame);
    }
    node->actions_sent++;
}

static void send_status(node_t *node)
{
    struct policy_dbc_node_status_t msg;
    can_frame_t frame = {POLICY_DBC_NODE_STATUS_FRAME_ID, POLICY_DBC_NODE_STATUS_LENGTH, {0}};
    memset(&msg, 0, sizeof msg);
    msg.counter = node->status_counter;
    msg.state = (uint8_t)node->state;
    msg.frames_ok = (uint16_t)saturate(node->frames_ok, U16_MAX);
    msg.crc_errors = (uint8_t)saturate(node->crc_errors, U8_MAX);
    msg.sequence_errors = (uint8_t)saturate(node->sequence_errors, U8_MAX);
    msg.timeouts = (uint8_t)saturate(node->timeouts, U8_MAX);
    msg.inference_us = (uint16_t)saturate(node->inference_us, INFERENCE_US_MAX);
    policy_dbc_node_status_pack(frame.data, &msg, sizeof frame.data);
    e2e_protect(frame.id, frame.data);
    node->status_counter = (uint8_t)((node->status_counter + 1u) % E2E_COUNTER_MODULO);
    (void)transport_send(&frame);
}

static void enter_safe(node_t *node, uint32_t now_ms)
{
    node->state = NODE_SAFE;
    node->consecutive_valid = 0;
    node->last_safe_ms = now_ms;
    send_action(node, safe_action, node->last_step);
    send_status(node);
}

static void complete_observation(node_t *node, uint32_t now_ms)
{
    float act[POLICY_ACT_DIM];
    node->last_valid_ms = now_ms;
    node->armed = true;
    node->consecutive_valid++;
    if (node->state == NODE_SAFE && node->consecutive_valid >= node->config.recover_count) {
        node->state = NODE_RUN;
    }
    if (node->state == NODE_SAFE) {
        send_action(node, safe_action, node->pending_step);
    } else {
        uint32_t start = clock_us();
        (void)policy_step(node->pending_obs, act); /* writes the safe action on any non-finite value */
        node->inference_us = clock_us() - start;
        send_action(node, act, node->pending_step);
    }
    node->last_step = node->pending_step;
    node->pending_valid = false;
    node->pending_parts = 0;
}

void node_on_frame(node_t *node, const can_frame_t *frame, uint32_t now_ms)
{
    if (frame->id < POLICY_IO_OBS_FIRST_ID || frame->id >= POLICY_IO_OBS_FIRST_ID + POLICY_IO_OBS_FRAMES ||
        frame->len != POLICY_IO_FRAME_BYTES) {
        node->rejected++;
        return;
    }
    unsigned part = (unsigned)(frame->id - POLICY_IO_OBS_FIRST_ID);
    if (!e2e_crc_ok(frame->id, frame->data)) {
        node->crc_errors++;
        node->consecutive_valid = 0;
        return;
    }
    /* Decode into a scratch copy: a frame rejected by its counter or a range must change nothing. */
    float scratch[POLICY_OBS_DIM];
    memcpy(scratch, node->pending_obs, sizeof scratch);
    uint16_t step = 0;
    uint8_t counter = 0;
    policy_io_status decoded = policy_io_decode_observation(part, frame->data, scratch, &step, &counter);
    e2e_status status = e2e_check_counter(&node->rx[part], counter);
    if (status != E2E_OK) {
        node->sequence_errors++; /* lost, repeated or out-of-order frames */
        node->consecutive_valid = 0;
    }
    if (status != E2E_OK && status != E2E_OK_SOME_LOST) {
        return;
    }
    if (decoded != POLICY_IO_OK) {
        node->range_errors++; /* a value the interface does not allow: never given to the policy */
        node->consecutive_valid = 0;
        return;
    }
    memcpy(node->pending_obs, scratch, sizeof scratch);
    node->frames_ok++;
    if (!node->pending_valid || step != node->pending_step) {
        if (node->pending_valid && node->pending_parts != 0u) {
            node->incomplete++; /* never assemble an observation from two steps */
        }
        /* keep only this frame's signals: the other parts must come from the same step */
        node->pending_valid = true;
        node->pending_step = step;
        node->pending_parts = 0;
    }
    node->pending_parts |= 1u << part;
    if (node->pending_parts == (uint32_t)((1ull << POLICY_IO_OBS_FRAMES) - 1u)) {
        complete_observation(node, now_ms);
    }
}

uint32_t node_poll(node_t *node, uint32_t now_ms)
{
    if (node->armed && node->state == NODE_RUN && now_ms - node->last_valid_ms >= node->config.timeout_ms) {
        node->timeouts++;
        enter_safe(node, now_ms);
    } else if (node->state == NODE_SAFE && now_ms - node->last_safe_ms >= node->config.timeout_ms &&
               now_ms - node->last_valid_ms >= node->config.timeout_ms) {
        node->last_safe_ms = now_ms; /* still silent: refresh the safe action */
        send_action(node, safe_action, node->last_step);
    }
    if ((int32_t)(now_ms - node->next_status_ms) >= 0) {
        send_status(node);
        node->next_status_ms = now_ms + node->config.status_period_ms;
    }
    uint32_t until_status = node->next_status_ms - now_ms;
    uint32_t until_watchdog = node->config.timeout_ms;
    if (node->armed && node->state == NODE_RUN) {
        uint32_t since = now_ms - node->last_valid_ms;
        until_watchdog = since >= node->config.timeout_ms ? 0u : node->config.timeout_ms - since;
    }
    return until_status < until_watchdog ? until_status : until_watchdog;
}
