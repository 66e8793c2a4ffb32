/*
 * The policy node: untrusted CAN frames in, actions and status out.
 *
 * Every frame is validated at the boundary (ID, length, CRC, alive counter, and each signal's range
 * in the DBC); only then are its signals used. The frame layout comes from code generated from the
 * policy's interface (policy_io.h: which fields travel in which frame; policy_dbc.h: cantools' codec).
 * An observation is the POLICY_IO_OBS_FRAMES frames of one Step; when all have arrived the policy runs
 * once and the action echoes the Step. Once the first observation has arrived, no valid observation
 * for timeout_ms -> SAFE: the export's safe action (POLICY_SAFE_ACTION) is sent (and repeated every
 * timeout_ms); back to RUN only after recover_count consecutive valid observations, answered with the
 * safe action until then. The node never acts on numbers it did not check: whatever policy_step
 * returns, an error status or an action that is non-finite or outside the interface's action range is
 * a fault (action_faults): the step is answered with the safe action, the node goes SAFE and recovers
 * as after a timeout. No malloc; every loop is bounded.
 *
 * Recovery rules (the README's table):
 * - alive counters re-synchronise after E2E_RESYNC_FRAMES consecutive counters outside the accepted
 *   window (a loss burst, a sender restart); the observation in flight is then incomplete;
 * - an observation whose Step is not after the last answered one (mod POLICY_IO_STEP_MODULO, half the
 *   range ahead) is a replay: dropped and counted, never answered. The step reference restarts after a
 *   counter re-synchronisation or a watchdog timeout (a restarted sender counts from 0 again);
 * - a failed interface (link down): SAFE, then node_link_restored once it is re-opened (main.c waits and
 *   retries, never exits); frames that cannot be sent are counted;
 * - error frames set the bus state (ERROR_PASSIVE, BUS_OFF, back to ACTIVE on restart), sent in NodeDiag.
 */
#ifndef EMBEDRL_NODE_H
#define EMBEDRL_NODE_H

#include <stdbool.h>
#include <stdint.h>

#include "e2e.h"
#include "platform.h"
#include "policy.h"
#include "policy_io.h"

typedef enum { NODE_RUN = 0, NODE_SAFE = 1 } node_state;
#define NODE_STATUS_START 2u /* NodeStatus's State while RUN with the policy at zero state (see node_t.fresh) */
typedef enum { NODE_BUS_ACTIVE = 0, NODE_BUS_PASSIVE = 1, NODE_BUS_OFF = 2 } node_bus_state;

typedef struct {
    uint32_t timeout_ms;
    uint32_t recover_count;
    uint32_t status_period_ms;
    uint32_t node_id; /* 0 .. POLICY_IO_MAX_NODES - 1: this node's IDs are node 0's offset by it */
} node_config;

typedef struct {
    node_config config;
    uint32_t obs_first_id; /* this node's IDs (from config.node_id) */
    uint32_t act_first_id;
    uint32_t status_id; /* NodeStatus; NodeDiag is the next ID */
    node_state state;
    /* counters reported in NodeStatus (saturating) */
    uint32_t frames_ok;
    uint32_t crc_errors;
    uint32_t sequence_errors;
    uint32_t timeouts;
    uint32_t inference_us;
    uint32_t rejected;     /* unknown ID or wrong length: dropped before any decoding */
    uint32_t range_errors; /* a signal outside its range in the DBC: frame dropped */
    uint32_t action_faults; /* policy outputs refused (non-finite, out of range, error status) */
    uint32_t incomplete; /* observation steps abandoned before all frames arrived */
    uint32_t stale_steps;   /* complete observations whose Step was not after the last answered one */
    uint32_t resyncs;       /* alive-counter re-synchronisations */
    uint32_t send_failures; /* frames the transport refused */
    uint32_t link_resets;   /* times the interface failed and was re-opened */
    uint32_t policy_resets; /* policy_reset calls: start-up, SAFE, EpisodeStart (a policy with memory) */
    bool fresh;             /* the policy is at zero state: no policy_step since the last reset */
    node_bus_state bus_state;
    uint32_t actions_sent;
    e2e_receiver rx[POLICY_IO_OBS_FRAMES];
    e2e_receiver episode_rx; /* EpisodeStart's alive counter (a policy with memory) */
    /* observation being assembled */
    bool pending_valid;
    uint16_t pending_step;
    uint32_t pending_parts; /* bit k: observation frame k of pending_step has arrived */
    float pending_obs[POLICY_OBS_DIM];
    uint16_t last_step;
    bool step_reference; /* last_step is a valid reference for the replay check */
    uint32_t last_valid_ms;
    uint32_t last_safe_ms;
    uint32_t next_status_ms;
    uint32_t consecutive_valid;
    bool armed; /* the watchdog runs from the first valid observation on */
    uint8_t action_counter[POLICY_IO_ACT_FRAMES];
    uint8_t status_counter;
    uint8_t diag_counter;
} node_t;

/* The CAN IDs node `node_id` receives: its observation frames and, for a policy with memory, its
 * EpisodeStart. */
#define NODE_RX_IDS (POLICY_IO_OBS_FRAMES + POLICY_IO_EPISODE_START)
void node_receive_ids(uint32_t node_id, uint32_t ids[NODE_RX_IDS]);

void node_init(node_t *node, const node_config *config, uint32_t now_ms);

/* Handle one received frame (sends the action when an observation completes). */
void node_on_frame(node_t *node, const can_frame_t *frame, uint32_t now_ms);

/* Time-driven duties: watchdog and periodic status. Returns the ms until the next deadline. */
uint32_t node_poll(node_t *node, uint32_t now_ms);

/* The interface failed (nothing can be sent or received): SAFE until it is back. */
void node_link_lost(node_t *node, uint32_t now_ms);

/* The interface was re-opened: announce SAFE with the safe action and the status; recovery as usual. */
void node_link_restored(node_t *node, uint32_t now_ms);

/* An error frame's controller state (from the transport): the bus state reported in NodeDiag. */
void node_on_bus_state(node_t *node, node_bus_state state);

#endif /* EMBEDRL_NODE_H */
