#include "node.h"

#include <string.h>

#include "policy_dbc.h"

#define U8_MAX 255u
#define U16_MAX 65535u
#define INFERENCE_US_MAX 1023u
#define RESYNCS_MAX 63u
#define LINK_RESETS_MAX 15u

/* The CAN glue sizes its vectors by the policy's own POLICY_OBS_DIM and POLICY_ACT_DIM (policy_io.h includes
 * policy.h): one set of dimensions. The receive-ID table holds every observation frame. */
typedef char node_frames_fit[(POLICY_IO_OBS_FRAMES <= 32u) ? 1 : -1];

static const float safe_action[POLICY_ACT_DIM] = POLICY_SAFE_ACTION;

static uint32_t saturate(uint32_t value, uint32_t max)
{
    return value > max ? max : value;
}

/* The policy's recurrent state back to zero (nothing to do for a policy without memory). */
static void reset_policy(node_t *node)
{
    policy_reset();
    node->policy_resets++;
    node->fresh = true;
}

void node_receive_ids(uint32_t node_id, uint32_t ids[NODE_RX_IDS])
{
    const uint32_t first = POLICY_IO_OBS_FIRST_ID + node_id * POLICY_IO_NODE_STRIDE;
    for (unsigned k = 0; k < POLICY_IO_OBS_FRAMES; ++k) {
        ids[k] = first + k;
    }
#if POLICY_IO_EPISODE_START
    ids[POLICY_IO_OBS_FRAMES] = first + POLICY_IO_EPISODE_START_OFFSET;
#endif
}

void node_init(node_t *node, const node_config *config, uint32_t now_ms)
{
    (void)memset(node, 0, sizeof *node);
    node->config = *config;
    node->obs_first_id = POLICY_IO_OBS_FIRST_ID + config->node_id * POLICY_IO_NODE_STRIDE;
    node->act_first_id = POLICY_IO_ACT_FIRST_ID + config->node_id * POLICY_IO_NODE_STRIDE;
    node->status_id = POLICY_IO_STATUS_ID + config->node_id * POLICY_IO_STATUS_STRIDE;
    node->state = NODE_RUN;
    node->last_valid_ms = now_ms;
    node->last_safe_ms = now_ms;
    node->next_status_ms = now_ms;
    reset_policy(node); /* a started (or restarted) node's policy has zero state */
}

static void send_frame(node_t *node, const can_frame_t *frame)
{
    if (transport_send(frame) != 0) {
        node->send_failures++; /* bus-off, link down or a full queue: visible in NodeDiag */
    }
}

static void send_action(node_t *node, const float act[POLICY_ACT_DIM], uint16_t step)
{
    for (unsigned part = 0; part < POLICY_IO_ACT_FRAMES; ++part) {
        can_frame_t frame = {node->act_first_id + part, POLICY_IO_FRAME_BYTES, {0}};
        /* every action is checked (policy_io_action_ok) before it gets here: nothing to saturate */
        (void)policy_io_encode_action(part, act, step, node->action_counter[part], frame.data);
        e2e_protect(frame.id, frame.data, frame.len);
        node->action_counter[part] = (uint8_t)((node->action_counter[part] + 1u) % E2E_COUNTER_MODULO);
        send_frame(node, &frame);
    }
    node->actions_sent++;
}

static void send_status(node_t *node)
{
    struct policy_dbc_node_status_t msg;
    can_frame_t frame = {node->status_id, POLICY_DBC_NODE_STATUS_LENGTH, {0}};
    (void)memset(&msg, 0, sizeof msg);
    msg.counter = node->status_counter;
    msg.state = (uint8_t)node->state;
    if ((node->state == NODE_RUN) && node->fresh) {
        msg.state = (uint8_t)NODE_STATUS_START;
    }
    msg.frames_ok = (uint16_t)saturate(node->frames_ok, U16_MAX);
    msg.crc_errors = (uint8_t)saturate(node->crc_errors, U8_MAX);
    msg.sequence_errors = (uint8_t)saturate(node->sequence_errors, U8_MAX);
    msg.timeouts = (uint8_t)saturate(node->timeouts, U8_MAX);
    msg.inference_us = (uint16_t)saturate(node->inference_us, INFERENCE_US_MAX);
    (void)policy_dbc_node_status_pack(frame.data, &msg, sizeof frame.data);
    e2e_protect(frame.id, frame.data, frame.len);
    node->status_counter = (uint8_t)((node->status_counter + 1u) % E2E_COUNTER_MODULO);
    send_frame(node, &frame);

    struct policy_dbc_node_diag_t diag;
    can_frame_t diag_frame = {node->status_id + 1u, POLICY_DBC_NODE_DIAG_LENGTH, {0}};
    (void)memset(&diag, 0, sizeof diag);
    diag.counter = node->diag_counter;
    diag.bus_state = (uint8_t)node->bus_state;
    diag.resyncs = (uint8_t)saturate(node->resyncs, RESYNCS_MAX);
    diag.range_errors = (uint8_t)saturate(node->range_errors, U8_MAX);
    diag.stale_steps = (uint8_t)saturate(node->stale_steps, U8_MAX);
    diag.incomplete = (uint8_t)saturate(node->incomplete, U8_MAX);
    diag.action_faults = (uint8_t)saturate(node->action_faults, U8_MAX);
    diag.send_failures = (uint8_t)saturate(node->send_failures, U8_MAX);
    diag.link_resets = (uint8_t)saturate(node->link_resets, LINK_RESETS_MAX);
    (void)policy_dbc_node_diag_pack(diag_frame.data, &diag, sizeof diag_frame.data);
    e2e_protect(diag_frame.id, diag_frame.data, diag_frame.len);
    node->diag_counter = (uint8_t)((node->diag_counter + 1u) % E2E_COUNTER_MODULO);
    send_frame(node, &diag_frame);
}

static void enter_safe(node_t *node, uint32_t now_ms)
{
    reset_policy(node); /* the safe state forgets the policy's memory: it restarts from zero */
    node->state = NODE_SAFE;
    node->consecutive_valid = 0;
    node->last_safe_ms = now_ms;
    node->step_reference = false; /* a sender that comes back may have restarted its steps */
    send_action(node, safe_action, node->last_step);
    send_status(node);
}

/* Whether `step` is after `last` on the Step circle: at most half of it ahead. */
static bool step_is_after(uint16_t step, uint16_t last)
{
    uint32_t ahead = ((uint32_t)step - last) % POLICY_IO_STEP_MODULO;
    return ahead != 0u && ahead < POLICY_IO_STEP_MODULO / 2u;
}

static void complete_observation(node_t *node, uint32_t now_ms)
{
    float act[POLICY_ACT_DIM];
    node->pending_valid = false;
    node->pending_parts = 0;
    if (node->step_reference && !step_is_after(node->pending_step, node->last_step)) {
        node->stale_steps++; /* a replayed or repeated step: never answered twice */
        node->consecutive_valid = 0;
        return;
    }
    node->step_reference = true;
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
        int32_t status = policy_step(node->pending_obs, act);
        node->fresh = false;
        node->inference_us = clock_us() - start;
        if (status == POLICY_OK && policy_io_action_ok(act)) {
            send_action(node, act, node->pending_step);
        } else {
            /* the status code alone is not trusted: the numbers themselves are checked */
            node->action_faults++;
            reset_policy(node);
            node->state = NODE_SAFE;
            node->consecutive_valid = 0;
            node->last_safe_ms = now_ms;
            send_action(node, safe_action, node->pending_step);
            send_status(node);
        }
    }
    node->last_step = node->pending_step;
}

/* The watchdog: no valid observation for the timeout while running -> SAFE. */
static void check_watchdog(node_t *node, uint32_t now_ms)
{
    if (node->armed && node->state == NODE_RUN && now_ms - node->last_valid_ms >= node->config.timeout_ms) {
        node->timeouts++;
        enter_safe(node, now_ms);
    }
}

/* A frame that is not one of this node's observation frames: a policy with memory's EpisodeStart
 * (E2E-checked, then the policy's state to zero for the episode's first observation), else rejected. */
static void not_an_observation(node_t *node, const can_frame_t *frame)
{
#if POLICY_IO_EPISODE_START
    if (frame->id == (node->obs_first_id + POLICY_IO_EPISODE_START_OFFSET)) {
        if ((frame->len != POLICY_DBC_EPISODE_START_LENGTH) || !e2e_crc_ok(frame->id, frame->data, frame->len)) {
            node->crc_errors++;
        } else {
            struct policy_dbc_episode_start_t msg;
            (void)policy_dbc_episode_start_unpack(&msg, frame->data, frame->len);
            e2e_status status = e2e_check_counter(&node->episode_rx, msg.counter);
            if ((status == E2E_OK) || (status == E2E_OK_SOME_LOST) || (status == E2E_OK_RESYNC)) {
                reset_policy(node);
            } else {
                node->sequence_errors++; /* a replayed EpisodeStart resets nothing */
            }
        }
    } else {
        node->rejected++;
    }
#else
    (void)frame;
    node->rejected++; /* not ours: another node's frame is never applied */
#endif
}

void node_on_frame(node_t *node, const can_frame_t *frame, uint32_t now_ms)
{
    /* A frame handled after the deadline is late whether or not the poll saw the deadline pass first. */
    check_watchdog(node, now_ms);
    if (frame->id < node->obs_first_id || frame->id >= node->obs_first_id + POLICY_IO_OBS_FRAMES ||
        frame->len != POLICY_IO_FRAME_BYTES) {
        not_an_observation(node, frame);
        return;
    }
    unsigned part = (unsigned)(frame->id - node->obs_first_id);
    if (!e2e_crc_ok(frame->id, frame->data, frame->len)) {
        node->crc_errors++;
        node->consecutive_valid = 0;
        return;
    }
    /* Decode into a scratch copy: a frame rejected by its counter or a range must change nothing. */
    float scratch[POLICY_OBS_DIM];
    (void)memcpy(scratch, node->pending_obs, sizeof scratch);
    uint16_t step = 0;
    uint8_t counter = 0;
    policy_io_status decoded = policy_io_decode_observation(part, frame->data, scratch, &step, &counter);
    e2e_status status = e2e_check_counter(&node->rx[part], counter);
    if (status != E2E_OK) {
        node->sequence_errors++; /* lost, repeated or out-of-order frames */
        node->consecutive_valid = 0;
    }
    if (status == E2E_OK_RESYNC) {
        node->resyncs++;
        node->step_reference = false; /* a new sequence: its steps may start anywhere */
    }
    if (status != E2E_OK && status != E2E_OK_SOME_LOST && status != E2E_OK_RESYNC) {
        return;
    }
    if (decoded != POLICY_IO_OK) {
        node->range_errors++; /* a value the interface does not allow: never given to the policy */
        node->consecutive_valid = 0;
        return;
    }
    (void)memcpy(node->pending_obs, scratch, sizeof scratch);
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
    if (node->pending_parts == (uint32_t)((1ULL << POLICY_IO_OBS_FRAMES) - 1u)) {
        complete_observation(node, now_ms);
    }
}

uint32_t node_poll(node_t *node, uint32_t now_ms)
{
    if (node->state == NODE_SAFE && now_ms - node->last_safe_ms >= node->config.timeout_ms &&
        now_ms - node->last_valid_ms >= node->config.timeout_ms) {
        node->last_safe_ms = now_ms; /* still silent: refresh the safe action */
        send_action(node, safe_action, node->last_step);
    }
    check_watchdog(node, now_ms); /* after the refresh: entering SAFE sends the safe action itself */
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

void node_link_lost(node_t *node, uint32_t now_ms)
{
    reset_policy(node);
    node->link_resets++;
    node->state = NODE_SAFE;
    node->consecutive_valid = 0;
    node->last_safe_ms = now_ms;
    node->step_reference = false;
    node->pending_valid = false;
    node->pending_parts = 0;
}

void node_link_restored(node_t *node, uint32_t now_ms)
{
    enter_safe(node, now_ms);
}

void node_on_bus_state(node_t *node, node_bus_state state)
{
    node->bus_state = state;
}
