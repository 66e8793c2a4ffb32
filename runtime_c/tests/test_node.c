/*
 * Unit tests of the policy node on the fake transport and clock: codec round trips for every
 * message, E2E rejections, observation assembly, watchdog and recovery, non-finite outputs.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "e2e.h"
#include "fake_platform.h"
#include "node.h"
#include "policy_dbc.h"
#include "policy_io.h"

static int failures;
static int checks;

#define CHECK(cond)                                                                                \
    do {                                                                                           \
        ++checks;                                                                                  \
        if (!(cond)) {                                                                             \
            ++failures;                                                                            \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);               \
        }                                                                                          \
    } while (0)

#define TIMEOUT_MS 100u
#define RECOVER 3u

static const node_config config = {TIMEOUT_MS, RECOVER, 1000u, 0u};
static uint8_t counters[3];

/* The three observation frames of one step, E2E protected, as the simulator sends them. */
static void make_observation(can_frame_t frames[3], uint16_t step, const float obs[6])
{
    struct policy_dbc_observation_a_t a;
    struct policy_dbc_observation_b_t b;
    struct policy_dbc_observation_c_t c;
    memset(&a, 0, sizeof a);
    memset(&b, 0, sizeof b);
    memset(&c, 0, sizeof c);
    a.counter = counters[0]++ & 15u;
    b.counter = counters[1]++ & 15u;
    c.counter = counters[2]++ & 15u;
    a.step = b.step = c.step = step;
    a.x = policy_dbc_observation_a_x_encode(obs[0]);
    a.y = policy_dbc_observation_a_y_encode(obs[1]);
    b.sin_theta = policy_dbc_observation_b_sin_theta_encode(obs[2]);
    b.cos_theta = policy_dbc_observation_b_cos_theta_encode(obs[3]);
    c.speed = policy_dbc_observation_c_speed_encode(obs[4]);
    c.turn_rate = policy_dbc_observation_c_turn_rate_encode(obs[5]);
    for (unsigned i = 0; i < 3; ++i) {
        frames[i].id = POLICY_DBC_OBSERVATION_A_FRAME_ID + i;
        frames[i].len = 8;
        memset(frames[i].data, 0, 8);
    }
    policy_dbc_observation_a_pack(frames[0].data, &a, 8);
    policy_dbc_observation_b_pack(frames[1].data, &b, 8);
    policy_dbc_observation_c_pack(frames[2].data, &c, 8);
    for (unsigned i = 0; i < 3; ++i) {
        e2e_protect(frames[i].id, frames[i].data, 8u);
    }
}

static void send_observation(node_t *node, uint16_t step, const float obs[6], uint32_t now_ms)
{
    can_frame_t frames[3];
    make_observation(frames, step, obs);
    for (unsigned i = 0; i < 3; ++i) {
        node_on_frame(node, &frames[i], now_ms);
    }
}

/* The last action frame sent, decoded; returns 0 if there is none. */
static int last_action(float act[2], uint16_t *step)
{
    for (unsigned i = fake_sent_count(); i-- > 0;) {
        const can_frame_t *f = fake_sent(i);
        if (f->id == POLICY_DBC_ACTION_FRAME_ID) {
            struct policy_dbc_action_t m;
            CHECK(e2e_crc_ok(f->id, f->data, f->len));
            policy_dbc_action_unpack(&m, f->data, 8);
            act[0] = (float)policy_dbc_action_force_left_decode(m.force_left);
            act[1] = (float)policy_dbc_action_force_right_decode(m.force_right);
            *step = m.step;
            return 1;
        }
    }
    return 0;
}

static unsigned count_actions(void)
{
    unsigned n = 0;
    for (unsigned i = 0; i < fake_sent_count(); ++i) {
        n += fake_sent(i)->id == POLICY_DBC_ACTION_FRAME_ID;
    }
    return n;
}

static void fresh(node_t *node)
{
    fake_reset();
    memset(counters, 0, sizeof counters);
    fake_set_ms(1000);
    node_init(node, &config, 1000);
}

static void test_codec_round_trips(void)
{
    uint8_t buf[8];
    struct policy_dbc_observation_a_t a, a2;
    memset(&a, 0, sizeof a); /* padding too: the round trip compares whole structs */
    memset(&a2, 0, sizeof a2);
    a.crc = 0xA5;
    a.counter = 9;
    a.step = 4095;
    a.x = policy_dbc_observation_a_x_encode(-1.75);
    a.y = policy_dbc_observation_a_y_encode(1.25);
    CHECK(policy_dbc_observation_a_pack(buf, &a, 8) == 8);
    CHECK(policy_dbc_observation_a_unpack(&a2, buf, 8) == 0);
    CHECK(memcmp(&a, &a2, sizeof a) == 0);
    CHECK(fabs(policy_dbc_observation_a_x_decode(a2.x) + 1.75) < 4e-6);

    struct policy_dbc_observation_b_t b, b2;
    memset(&b, 0, sizeof b); /* padding too: the round trip compares whole structs */
    memset(&b2, 0, sizeof b2);
    b.counter = 15;
    b.step = 17;
    b.sin_theta = policy_dbc_observation_b_sin_theta_encode(-1.0);
    b.cos_theta = policy_dbc_observation_b_cos_theta_encode(1.0);
    CHECK(policy_dbc_observation_b_pack(buf, &b, 8) == 8);
    CHECK(policy_dbc_observation_b_unpack(&b2, buf, 8) == 0 && memcmp(&b, &b2, sizeof b) == 0);
    CHECK(policy_dbc_observation_b_cos_theta_decode(b2.cos_theta) == 1.0);

    struct policy_dbc_observation_c_t c, c2;
    memset(&c, 0, sizeof c); /* padding too: the round trip compares whole structs */
    memset(&c2, 0, sizeof c2);
    c.step = 1;
    c.speed = policy_dbc_observation_c_speed_encode(0.7);
    c.turn_rate = policy_dbc_observation_c_turn_rate_encode(-2.0);
    CHECK(policy_dbc_observation_c_pack(buf, &c, 8) == 8);
    CHECK(policy_dbc_observation_c_unpack(&c2, buf, 8) == 0 && memcmp(&c, &c2, sizeof c) == 0);
    CHECK(policy_dbc_observation_c_turn_rate_decode(c2.turn_rate) == -2.0);

    struct policy_dbc_action_t act, act2;
    memset(&act, 0, sizeof act); /* padding too: the round trip compares whole structs */
    memset(&act2, 0, sizeof act2);
    act.counter = 3;
    act.step = 200;
    act.force_left = policy_dbc_action_force_left_encode(-1.0);
    act.force_right = policy_dbc_action_force_right_encode(0.123456);
    CHECK(policy_dbc_action_pack(buf, &act, 8) == 8);
    CHECK(policy_dbc_action_unpack(&act2, buf, 8) == 0 && memcmp(&act, &act2, sizeof act) == 0);
    CHECK(fabs(policy_dbc_action_force_right_decode(act2.force_right) - 0.123456) < 4e-6);

    struct policy_dbc_node_status_t s, s2;
    memset(&s, 0, sizeof s); /* padding too: the round trip compares whole structs */
    memset(&s2, 0, sizeof s2);
    s.counter = 7;
    s.state = 1;
    s.frames_ok = 65535;
    s.crc_errors = 255;
    s.sequence_errors = 1;
    s.timeouts = 2;
    s.inference_us = 1023;
    CHECK(policy_dbc_node_status_pack(buf, &s, 8) == 8);
    CHECK(policy_dbc_node_status_unpack(&s2, buf, 8) == 0 && memcmp(&s, &s2, sizeof s) == 0);
}

static void test_crc8_reference_vector(void)
{
    /* CRC-8 SAE J1850 of "123456789" is 0x4B; here the first two bytes go through the data ID. */
    const uint8_t data[8] = {0, '3', '4', '5', '6', '7', '8', '9'};
    CHECK(e2e_crc8((uint32_t)'1' | ((uint32_t)'2' << 8), data, 8u) == 0x4Bu);
}

static void test_valid_observation_gives_one_action(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {1.0f, 0.5f, 0.0f, 1.0f, 0.1f, 0.2f};
    send_observation(&node, 42, obs, 1000);
    float act[2];
    uint16_t step;
    CHECK(count_actions() == 1);
    CHECK(last_action(act, &step) && step == 42);
    CHECK(fabsf(act[0] - 0.5f) < 4e-6f && fabsf(act[1] - 0.25f) < 4e-6f);
    CHECK(node.frames_ok == 3 && node.crc_errors == 0 && node.sequence_errors == 0);
}

static void test_e2e_rejections(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.2f, 0.2f, 0.0f, 1.0f, 0.0f, 0.0f};
    can_frame_t frames[3];

    /* corrupted payload bit: CRC error, dropped, no action */
    make_observation(frames, 1, obs);
    frames[1].data[5] ^= 0x10u;
    for (unsigned i = 0; i < 3; ++i) {
        node_on_frame(&node, &frames[i], 1000);
    }
    CHECK(node.crc_errors == 1 && count_actions() == 0);

    /* foreign frame: a valid frame of ObservationA sent under ObservationB's ID (wrong data ID) */
    make_observation(frames, 2, obs);
    can_frame_t foreign = frames[0];
    foreign.id = POLICY_DBC_OBSERVATION_B_FRAME_ID;
    node_on_frame(&node, &foreign, 1000);
    CHECK(node.crc_errors == 2);

    /* a complete valid step still works */
    for (unsigned i = 0; i < 3; ++i) {
        node_on_frame(&node, &frames[i], 1000);
    }
    CHECK(count_actions() == 1);

    /* repeated frame (same counter): sequence error, no second action */
    node_on_frame(&node, &frames[2], 1000);
    CHECK(node.sequence_errors == 1 && count_actions() == 1);

    /* lost frames: a forward jump of the counter is accepted and counted */
    uint32_t ok_before = node.frames_ok;
    counters[0] = (uint8_t)(counters[0] + 2u);
    make_observation(frames, 3, obs);
    node_on_frame(&node, &frames[0], 1000);
    CHECK(node.sequence_errors == 2 && node.frames_ok == ok_before + 1);

    /* out of order: an older counter */
    can_frame_t older[3];
    counters[0] = (uint8_t)(counters[0] - 3u);
    make_observation(older, 3, obs);
    node_on_frame(&node, &older[0], 1000);
    CHECK(node.sequence_errors == 3 && node.frames_ok == ok_before + 1);

    /* wrong length and unknown ID are rejected before decoding */
    can_frame_t short_frame = frames[0];
    short_frame.len = 7;
    node_on_frame(&node, &short_frame, 1000);
    can_frame_t unknown = frames[0];
    unknown.id = 0x123;
    node_on_frame(&node, &unknown, 1000);
    CHECK(node.rejected == 2);
}

static void test_never_assembles_two_steps(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.4f, 0.4f, 0.0f, 1.0f, 0.0f, 0.0f};
    can_frame_t step5[3], step6[3];
    make_observation(step5, 5, obs);
    make_observation(step6, 6, obs);
    node_on_frame(&node, &step5[0], 1000);
    node_on_frame(&node, &step5[1], 1000);
    node_on_frame(&node, &step6[2], 1000); /* the last part, but of the next step */
    CHECK(count_actions() == 0 && node.incomplete == 1);
    node_on_frame(&node, &step6[0], 1000);
    node_on_frame(&node, &step6[1], 1000);
    float act[2];
    uint16_t step;
    CHECK(count_actions() == 1 && last_action(act, &step) && step == 6);
}

static void test_watchdog_safe_and_recovery(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    float act[2];
    uint16_t step;
    /* before the first observation the watchdog is not armed */
    node_poll(&node, 1000 + 10 * TIMEOUT_MS);
    CHECK(node.state == NODE_RUN && node.timeouts == 0);
    send_observation(&node, 1, obs, 2000);
    node_poll(&node, 2000 + TIMEOUT_MS - 1);
    CHECK(node.state == NODE_RUN && count_actions() == 1);
    node_poll(&node, 2000 + TIMEOUT_MS);
    CHECK(node.state == NODE_SAFE && node.timeouts == 1);
    /* the policy's own safe action (POLICY_SAFE_ACTION), not zeros */
    CHECK(count_actions() == 2 && last_action(act, &step) && act[0] == 0.25f && act[1] == -0.5f);
    /* still silent: the safe action is repeated every timeout */
    node_poll(&node, 2000 + 2 * TIMEOUT_MS);
    CHECK(count_actions() == 3);
    /* recovery needs RECOVER consecutive valid observations; until then the safe action answers */
    uint32_t t = 2000 + 2 * TIMEOUT_MS + 10;
    for (uint16_t s = 2; s < 2 + RECOVER - 1; ++s) {
        send_observation(&node, s, obs, t);
        CHECK(node.state == NODE_SAFE && last_action(act, &step) && step == s && act[0] == 0.25f);
    }
    /* a corrupted frame restarts the count */
    can_frame_t frames[3];
    make_observation(frames, 9, obs);
    frames[0].data[3] ^= 1u;
    node_on_frame(&node, &frames[0], t);
    for (uint16_t s = 10; s < 10 + RECOVER - 1; ++s) {
        send_observation(&node, s, obs, t);
        CHECK(node.state == NODE_SAFE);
    }
    send_observation(&node, 20, obs, t);
    CHECK(node.state == NODE_RUN && last_action(act, &step) && step == 20 && fabsf(act[0] - 0.5f) < 4e-6f);
}

static void test_the_policy_memory_is_reset_at_start_up_and_in_the_safe_state(void)
{
    node_t node;
    const unsigned before = fake_policy_resets;
    fresh(&node);
    CHECK(fake_policy_resets == before + 1u && node.policy_resets == 1u); /* start-up: zero state */
    const float obs[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 2000);
    send_observation(&node, 2, obs, 2010);
    CHECK(node.policy_resets == 1u); /* running steps carry the state */
    node_poll(&node, 2010 + TIMEOUT_MS);
    CHECK(node.state == NODE_SAFE && node.policy_resets == 2u); /* the watchdog: the state is forgotten */
    const float overflow[6] = {1.7f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f};
    node_t faulty;
    fresh(&faulty);
    send_observation(&faulty, 3, overflow, 1000);
    CHECK(faulty.state == NODE_SAFE && faulty.policy_resets == 2u); /* a policy fault too */
    node_link_lost(&faulty, 1100);
    CHECK(faulty.policy_resets == 3u);
}

static void test_a_late_frame_counts_the_timeout_without_a_poll(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    float act[2];
    uint16_t step;
    send_observation(&node, 1, obs, 2000);
    /* the next step arrives after the deadline and no poll ran between (a busy or descheduled node) */
    send_observation(&node, 2, obs, 2000 + TIMEOUT_MS + 1);
    CHECK(node.state == NODE_SAFE && node.timeouts == 1);
    CHECK(last_action(act, &step) && step == 2 && act[0] == 0.25f && act[1] == -0.5f);
}

static void test_non_finite_output_gives_the_safe_action(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {1.7f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f}; /* the fake network overflows */
    send_observation(&node, 7, obs, 1000);
    float act[2];
    uint16_t step;
    CHECK(last_action(act, &step) && step == 7 && act[0] == 0.25f && act[1] == -0.5f);
    CHECK(node.action_faults == 1u && node.state == NODE_SAFE); /* an error status is a fault too */
}

static void test_actions_outside_their_range_are_saturated_not_wrapped(void)
{
    /* 20-bit signals: without saturation 2.5 would arrive as -1.5 (a sign-flipped wheel force). */
    const float act[2] = {2.5f, -30000.0f};
    uint8_t data[8];
    CHECK(!policy_io_action_ok(act));
    CHECK(policy_io_encode_action(0u, act, 5u, 0u, data) == 2u);
    struct policy_dbc_action_t m;
    CHECK(policy_dbc_action_unpack(&m, data, 8) == 0);
    CHECK(policy_dbc_action_force_left_decode(m.force_left) == 1.0);
    CHECK(policy_dbc_action_force_right_decode(m.force_right) == -1.0);
    const float inside[2] = {0.25f, -1.0f};
    CHECK(policy_io_action_ok(inside));
    CHECK(policy_io_encode_action(0u, inside, 6u, 1u, data) == 0u);
    CHECK(policy_dbc_action_unpack(&m, data, 8) == 0 && m.step == 6u);
    CHECK(policy_dbc_action_force_left_decode(m.force_left) == 0.25);
    const float rounding[2] = {1.0000002f, -1.0000001f}; /* onnxruntime's tanh: the bound after rounding */
    CHECK(policy_io_action_ok(rounding));
    const float beyond[2] = {1.00001f, 0.0f};
    CHECK(!policy_io_action_ok(beyond));
    const float nan_inf[2][2] = {{NAN, 0.0f}, {0.0f, -INFINITY}};
    CHECK(!policy_io_action_ok(nan_inf[0]) && !policy_io_action_ok(nan_inf[1]));
}

/* A policy that returns POLICY_OK with NaN or an out-of-range action: the node checks the numbers. */
static void test_a_policy_that_lies_about_its_status_gets_the_safe_action(void)
{
    const float lies[2] = {FAKE_POLICY_NAN_SIN, FAKE_POLICY_OUT_OF_RANGE_SIN};
    for (unsigned k = 0; k < 2; ++k) {
        node_t node;
        fresh(&node);
        float act[2];
        uint16_t step;
        const float good[6] = {0.4f, 0.2f, 0.0f, 1.0f, 0.0f, 0.0f};
        send_observation(&node, 1, good, 1000);
        CHECK(last_action(act, &step) && step == 1 && fabsf(act[0] - 0.2f) < 4e-6f);
        const float bad[6] = {0.4f, 0.2f, lies[k], 0.8f, 0.0f, 0.0f};
        send_observation(&node, 2, bad, 1010);
        CHECK(last_action(act, &step) && step == 2 && act[0] == 0.25f && act[1] == -0.5f);
        CHECK(node.action_faults == 1u && node.state == NODE_SAFE);
        /* the fault is announced at once: NodeStatus State SAFE, NodeDiag ActionFaults 1 */
        const can_frame_t *status = fake_sent(fake_sent_count() - 2u);
        const can_frame_t *diag = fake_sent(fake_sent_count() - 1u);
        struct policy_dbc_node_status_t s;
        struct policy_dbc_node_diag_t d;
        CHECK(status->id == POLICY_DBC_NODE_STATUS_FRAME_ID && diag->id == POLICY_DBC_NODE_DIAG_FRAME_ID);
        policy_dbc_node_status_unpack(&s, status->data, 8);
        policy_dbc_node_diag_unpack(&d, diag->data, 8);
        CHECK(s.state == 1u && d.action_faults == 1u);
        /* recovery as after a timeout: RECOVER valid observations answered safe, then the policy again */
        uint32_t t = 1020;
        for (uint16_t st = 3; st < 3u + RECOVER - 1u; ++st, t += 10) {
            send_observation(&node, st, good, t);
            CHECK(last_action(act, &step) && step == st && act[0] == 0.25f && node.state == NODE_SAFE);
        }
        send_observation(&node, (uint16_t)(3u + RECOVER - 1u), good, t);
        CHECK(node.state == NODE_RUN && last_action(act, &step) && fabsf(act[0] - 0.2f) < 4e-6f);
    }
}

static void test_a_value_outside_its_range_is_never_given_to_the_policy(void)
{
    node_t node;
    fresh(&node);
    /* y = -0.5 m is below the interface's -0.15 m: the frame carrying it is dropped and counted */
    const float bad[6] = {1.0f, -0.5f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 3, bad, 1000);
    CHECK(count_actions() == 0 && node.range_errors == 1 && node.frames_ok == 2);
    /* the frames of the next step are all in range: one action, computed from them only */
    const float good[6] = {1.0f, 1.3f, 0.0f, 1.0f, 0.0f, 0.0f}; /* y exactly at its upper bound */
    send_observation(&node, 4, good, 1010);
    float act[2];
    uint16_t step;
    CHECK(count_actions() == 1 && last_action(act, &step) && step == 4 && fabsf(act[1] - 0.65f) < 4e-6f);
    CHECK(node.range_errors == 1 && node.incomplete == 1);
}

static unsigned status_state(node_t *node, uint32_t now_ms)
{
    fake_reset();
    node->next_status_ms = now_ms;
    node_poll(node, now_ms);
    struct policy_dbc_node_status_t s;
    policy_dbc_node_status_unpack(&s, fake_sent(0)->data, 8);
    return s.state;
}

static void test_a_started_node_says_its_policy_is_at_zero_state_until_its_first_step(void)
{
    node_t node;
    fresh(&node);
    CHECK(status_state(&node, 1000) == NODE_STATUS_START);
    const float obs[6] = {0.1f, 0.1f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 1000);
    CHECK(status_state(&node, 1010) == 0u); /* RUN */
    node_poll(&node, 1000 + TIMEOUT_MS);
    CHECK(status_state(&node, 1000 + TIMEOUT_MS) == 1u); /* SAFE outranks the reset it made */
}

static void test_status_frame_reports_counters(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.1f, 0.1f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 1000);
    fake_reset();
    node_poll(&node, 1000);
    CHECK(fake_sent_count() >= 1);
    const can_frame_t *f = fake_sent(0);
    struct policy_dbc_node_status_t s;
    CHECK(f->id == POLICY_DBC_NODE_STATUS_FRAME_ID && e2e_crc_ok(f->id, f->data, f->len));
    policy_dbc_node_status_unpack(&s, f->data, 8);
    CHECK(s.state == 0 && s.frames_ok == 3 && s.crc_errors == 0);
}

static void test_counters_resynchronise_after_a_loss_burst_or_a_sender_restart(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.3f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f};
    float act[2];
    uint16_t step;
    send_observation(&node, 10, obs, 1000);
    CHECK(count_actions() == 1);
    /* 9 frames of each message lost: beyond the forward window, the next step is dropped ... */
    for (unsigned i = 0; i < 3; ++i) {
        counters[i] = (uint8_t)(counters[i] + 9u);
    }
    send_observation(&node, 11, obs, 1010);
    CHECK(count_actions() == 1 && node.sequence_errors == 3 && node.resyncs == 0);
    /* ... and the second consecutive one re-establishes the sequences and is answered */
    send_observation(&node, 12, obs, 1020);
    CHECK(count_actions() == 2 && node.resyncs == 3 && last_action(act, &step) && step == 12);
    /* a sender restart: counters and steps from 0 again; answered from its second step on */
    counters[0] = counters[1] = counters[2] = 4u; /* 9 ahead of the node's last ones: outside the window */
    send_observation(&node, 0, obs, 1030);
    send_observation(&node, 1, obs, 1040);
    CHECK(count_actions() == 3 && last_action(act, &step) && step == 1 && node.stale_steps == 0);
    send_observation(&node, 2, obs, 1050);
    CHECK(count_actions() == 4 && last_action(act, &step) && step == 2);
}

static void test_a_step_that_goes_backwards_is_never_answered(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.3f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f};
    float act[2];
    uint16_t step;
    send_observation(&node, 104, obs, 1000);
    send_observation(&node, 7, obs, 1010);    /* backwards, with fresh counters and good CRCs */
    send_observation(&node, 104, obs, 1020);  /* the same step again */
    CHECK(count_actions() == 1 && node.stale_steps == 2);
    send_observation(&node, 105, obs, 1030);
    CHECK(count_actions() == 2 && last_action(act, &step) && step == 105);
    /* steps wrap around modulo POLICY_IO_STEP_MODULO */
    send_observation(&node, POLICY_IO_STEP_MODULO - 1u, obs, 1040);
    CHECK(count_actions() == 2 && node.stale_steps == 3); /* half the circle ahead: behind */
    fresh(&node);
    send_observation(&node, POLICY_IO_STEP_MODULO - 1u, obs, 1000);
    send_observation(&node, 0, obs, 1010);
    CHECK(count_actions() == 2 && node.stale_steps == 0 && last_action(act, &step) && step == 0);
    /* after a watchdog timeout a sender may start again from any step */
    node_poll(&node, 1010 + TIMEOUT_MS);
    CHECK(node.state == NODE_SAFE);
    send_observation(&node, 4000, obs, 1200); /* behind step 0, but a new reference */
    CHECK(node.stale_steps == 0 && last_action(act, &step) && step == 4000);
}

static void test_link_loss_send_failures_and_bus_state_are_reported(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {0.3f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f};
    float act[2];
    uint16_t step;
    send_observation(&node, 1, obs, 1000);
    fake_fail_sends(true);
    node_link_lost(&node, 1010);
    CHECK(node.state == NODE_SAFE && node.link_resets == 1);
    node_poll(&node, 1010 + TIMEOUT_MS); /* status and the repeated safe action cannot go out */
    CHECK(node.send_failures >= 2);
    fake_fail_sends(false);
    fake_reset();
    node_link_restored(&node, 1200);
    CHECK(count_actions() == 1 && last_action(act, &step) && act[0] == 0.25f && act[1] == -0.5f);
    for (uint16_t s = 0; s < RECOVER; ++s) { /* the restarted link may bring a restarted sender */
        send_observation(&node, s, obs, 1210 + s);
    }
    CHECK(node.state == NODE_RUN && last_action(act, &step) && step == RECOVER - 1u);
    node_on_bus_state(&node, NODE_BUS_OFF);
    fake_reset();
    node_poll(&node, 100000);
    const can_frame_t *diag = NULL;
    for (unsigned i = 0; i < fake_sent_count(); ++i) {
        if (fake_sent(i)->id == POLICY_DBC_NODE_DIAG_FRAME_ID) {
            diag = fake_sent(i);
        }
    }
    CHECK(diag != NULL && e2e_crc_ok(diag->id, diag->data, diag->len));
    if (diag != NULL) {
        struct policy_dbc_node_diag_t d;
        policy_dbc_node_diag_unpack(&d, diag->data, 8);
        CHECK(d.bus_state == NODE_BUS_OFF && d.link_resets == 1 && d.send_failures == node.send_failures);
    }
}

static void test_a_node_answers_only_its_own_ids(void)
{
    const node_config second = {TIMEOUT_MS, RECOVER, 1000u, 2u};
    node_t node;
    fresh(&node);
    node_init(&node, &second, 1000);
    const float obs[6] = {0.3f, 0.3f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 1000); /* node 0's IDs: not for node 2 */
    CHECK(fake_sent_count() == 0 && node.rejected == 3 && node.frames_ok == 0);
    can_frame_t frames[3];
    make_observation(frames, 2, obs);
    for (unsigned i = 0; i < 3; ++i) { /* the same observation under node 2's IDs, CRC over them */
        frames[i].id += 2u * POLICY_IO_NODE_STRIDE;
        e2e_protect(frames[i].id, frames[i].data, 8u);
        node_on_frame(&node, &frames[i], 1000);
    }
    CHECK(fake_sent_count() == 1);
    const can_frame_t *action = fake_sent(0);
    CHECK(action->id == POLICY_DBC_ACTION_FRAME_ID + 2u * POLICY_IO_NODE_STRIDE && e2e_crc_ok(action->id, action->data, action->len));
    fake_reset();
    node_poll(&node, 1000);
    CHECK(fake_sent_count() == 2 && fake_sent(0)->id == POLICY_IO_STATUS_ID + 4u && fake_sent(1)->id == POLICY_IO_DIAG_ID + 4u);
}

static void test_counters_saturate_in_the_status_frame(void)
{
    node_t node;
    fresh(&node);
    node.frames_ok = 70000u; /* above the 16-bit field */
    node.crc_errors = 1000u; /* above the 8-bit field */
    fake_reset();
    node_poll(&node, 1000);
    struct policy_dbc_node_status_t s;
    policy_dbc_node_status_unpack(&s, fake_sent(0)->data, 8);
    CHECK(s.frames_ok == 65535u && s.crc_errors == 255u && s.sequence_errors == 0u);
}

static void test_receive_ids_are_the_nodes_observation_frames(void)
{
    uint32_t ids[NODE_RX_IDS];
    node_receive_ids(1u, ids);
    for (unsigned k = 0; k < POLICY_IO_OBS_FRAMES; ++k) {
        CHECK(ids[k] == POLICY_IO_OBS_FIRST_ID + POLICY_IO_NODE_STRIDE + k);
    }
}

static void test_the_safe_action_is_refreshed_only_after_a_timeout_without_valid_frames(void)
{
    node_t node;
    fresh(&node);
    const float obs[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 2000);
    node_poll(&node, 2000 + TIMEOUT_MS); /* SAFE, its safe action sent */
    send_observation(&node, 2, obs, 2000 + TIMEOUT_MS + 50); /* answered, still SAFE (RECOVER > 1) */
    unsigned sent = count_actions();
    node_poll(&node, 2000 + 2 * TIMEOUT_MS); /* a timeout since the last safe action, not since the frame */
    CHECK(node.state == NODE_SAFE && count_actions() == sent);
    node_poll(&node, 2000 + 2 * TIMEOUT_MS + 50); /* now silent for a timeout: refreshed */
    CHECK(count_actions() == sent + 1u);
}

static void test_poll_returns_the_nearest_deadline(void)
{
    node_t node;
    fresh(&node);
    CHECK(node_poll(&node, 1000) == TIMEOUT_MS); /* status sent, next in 1000 ms; the watchdog's period */
    CHECK(node_poll(&node, 1950) == 50u);        /* the status is due first */
    const float obs[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    send_observation(&node, 1, obs, 2010);
    CHECK(node_poll(&node, 2030) == TIMEOUT_MS - 20u); /* armed: the watchdog's remaining time */
}

static void test_the_crc_covers_at_most_a_can_fd_frame(void)
{
    uint8_t a[E2E_MAX_FRAME_BYTES + 6u];
    uint8_t b[E2E_MAX_FRAME_BYTES + 6u];
    for (unsigned i = 0; i < sizeof a; ++i) {
        a[i] = b[i] = (uint8_t)(7u * i + 1u);
    }
    b[E2E_MAX_FRAME_BYTES + 2u] ^= 0xFFu; /* beyond the bound: never read */
    e2e_protect(0x123u, a, E2E_MAX_FRAME_BYTES);
    e2e_protect(0x123u, b, (unsigned)sizeof b);
    CHECK(a[0] == b[0]);
}

static void test_a_counter_that_does_not_follow_the_candidate_restarts_its_run(void)
{
    e2e_receiver rx;
    memset(&rx, 0, sizeof rx);
    CHECK(e2e_check_counter(&rx, 0u) == E2E_OK);
    CHECK(e2e_check_counter(&rx, 9u) == E2E_WRONG_SEQUENCE);  /* outside the window: a candidate */
    CHECK(e2e_check_counter(&rx, 12u) == E2E_WRONG_SEQUENCE); /* does not follow 9: a new candidate */
    CHECK(rx.candidate == 12u && rx.candidate_run == 1u && rx.last_counter == 0u);
    CHECK(e2e_check_counter(&rx, 13u) == E2E_OK_RESYNC);      /* follows 12 */
}

static void test_each_observation_signal_outside_its_range_drops_its_frame(void)
{
    const float good[6] = {1.0f, 1.0f, 0.0f, 1.0f, 0.0f, 0.0f};
    const float bad[6] = {-1.9f, 1.4f, -1.1f, 1.1f, -0.8f, 2.1f}; /* each just outside its range */
    for (unsigned i = 0; i < 6u; ++i) {
        node_t node;
        fresh(&node);
        float obs[6];
        memcpy(obs, good, sizeof obs);
        obs[i] = bad[i];
        send_observation(&node, 1, obs, 1000);
        CHECK(node.range_errors == 1u && count_actions() == 0u);
    }
}

static void test_actions_are_checked_against_both_bounds_of_each_field(void)
{
    const float ok[2] = {-1.0f, 1.0f};
    const float low0[2] = {-1.5f, 0.0f};
    const float high0[2] = {1.5f, 0.0f};
    const float low1[2] = {0.0f, -1.5f};
    const float high1[2] = {0.0f, 1.5f};
    CHECK(policy_io_action_ok(ok));
    CHECK(!policy_io_action_ok(low0) && !policy_io_action_ok(high0));
    CHECK(!policy_io_action_ok(low1) && !policy_io_action_ok(high1));
}

static void test_the_glue_refuses_a_frame_number_the_interface_does_not_have(void)
{
    uint8_t data[POLICY_IO_FRAME_BYTES];
    float obs[POLICY_OBS_DIM];
    uint16_t step = 7u;
    uint8_t counter = 3u;
    memset(data, 0, sizeof data);
    CHECK(policy_io_decode_observation(POLICY_IO_OBS_FRAMES, data, obs, &step, &counter) == POLICY_IO_OUT_OF_RANGE);
    const float act[2] = {0.5f, -0.5f};
    memset(data, 0xAA, sizeof data);
    CHECK(policy_io_encode_action(POLICY_IO_ACT_FRAMES, act, 1u, 0u, data) == 0u);
    for (unsigned i = 0; i < POLICY_IO_FRAME_BYTES; ++i) {
        CHECK(data[i] == 0u); /* cleared, nothing packed */
    }
}

int main(void)
{
    test_codec_round_trips();
    test_crc8_reference_vector();
    test_valid_observation_gives_one_action();
    test_e2e_rejections();
    test_never_assembles_two_steps();
    test_watchdog_safe_and_recovery();
    test_a_late_frame_counts_the_timeout_without_a_poll();
    test_the_policy_memory_is_reset_at_start_up_and_in_the_safe_state();
    test_non_finite_output_gives_the_safe_action();
    test_a_value_outside_its_range_is_never_given_to_the_policy();
    test_actions_outside_their_range_are_saturated_not_wrapped();
    test_a_policy_that_lies_about_its_status_gets_the_safe_action();
    test_status_frame_reports_counters();
    test_a_started_node_says_its_policy_is_at_zero_state_until_its_first_step();
    test_counters_resynchronise_after_a_loss_burst_or_a_sender_restart();
    test_a_step_that_goes_backwards_is_never_answered();
    test_link_loss_send_failures_and_bus_state_are_reported();
    test_a_node_answers_only_its_own_ids();
    test_counters_saturate_in_the_status_frame();
    test_receive_ids_are_the_nodes_observation_frames();
    test_the_safe_action_is_refreshed_only_after_a_timeout_without_valid_frames();
    test_poll_returns_the_nearest_deadline();
    test_the_crc_covers_at_most_a_can_fd_frame();
    test_a_counter_that_does_not_follow_the_candidate_restarts_its_run();
    test_each_observation_signal_outside_its_range_drops_its_frame();
    test_actions_are_checked_against_both_bounds_of_each_field();
    test_the_glue_refuses_a_frame_number_the_interface_does_not_have();
    printf("%d checks, %d failures\n", checks, failures);
    return failures == 0 ? 0 : 1;
}
