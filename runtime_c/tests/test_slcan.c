/*
 * Unit tests of the firmware node's serial CAN framing (cortex_m/slcan.c) on the host: encode, decode,
 * the adapter commands, corrupt and overlong lines, and receive-ring overflow.
 */
#include <stdio.h>
#include <string.h>

#include "slcan.h"

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

static void push_text(slcan_rx *rx, const char *text)
{
    for (size_t i = 0; text[i] != '\0'; ++i) {
        slcan_rx_push(rx, (uint8_t)text[i]);
    }
}

static void test_encode_is_the_lawicel_line(void)
{
    can_frame_t frame = {0x123u, 4u, {0xAAu, 0x0Bu, 0xC0u, 0xFFu}};
    char line[SLCAN_MAX_LINE];
    uint32_t n = slcan_encode(&frame, line);
    CHECK(n == 14u && memcmp(line, "t1234AA0BC0FF\r", 14) == 0);
    can_frame_t full = {0x7FFu, 8u, {1, 2, 3, 4, 5, 6, 7, 8}};
    CHECK(slcan_encode(&full, line) == SLCAN_FRAME_LINE);
    can_frame_t extended = {0x800u, 1u, {0}};
    CHECK(slcan_encode(&extended, line) == 0u); /* not a standard ID: refused, never truncated */
    can_frame_t fd = {0x100u, 12u, {0}};
    CHECK(slcan_encode(&fd, line) == 0u);
}

static void test_decode_round_trips_every_length(void)
{
    for (uint8_t len = 0u; len <= 8u; ++len) {
        can_frame_t in = {0x2A5u, len, {0}};
        for (uint8_t i = 0u; i < len; ++i) {
            in.data[i] = (uint8_t)(0x11u * (i + 1u));
        }
        char line[SLCAN_MAX_LINE];
        uint32_t n = slcan_encode(&in, line);
        can_frame_t out;
        memset(&out, 0xEE, sizeof out);
        CHECK(slcan_decode(line, n - 1u, &out));
        CHECK(out.id == in.id && out.len == len && memcmp(out.data, in.data, len) == 0);
    }
    can_frame_t out;
    CHECK(slcan_decode("t1232abcd", 9u, &out) && out.data[0] == 0xABu); /* lower-case hex is accepted */
}

static void test_corrupt_lines_are_refused(void)
{
    can_frame_t out;
    CHECK(!slcan_decode("t12", 3u, &out));            /* too short */
    CHECK(!slcan_decode("t1239AABB", 9u, &out));      /* length digit 9 */
    CHECK(!slcan_decode("t1232AABBCC", 11u, &out));   /* more data than its length */
    CHECK(!slcan_decode("t1232AAB", 8u, &out));       /* less */
    CHECK(!slcan_decode("t12G1AA", 7u, &out));        /* not hex */
    CHECK(!slcan_decode("T000001231AA", 12u, &out));  /* extended ID */
    CHECK(!slcan_decode("r1230", 5u, &out));          /* remote frame */
}

static void test_commands_open_the_channel_and_frames_pass_only_when_open(void)
{
    static slcan_rx rx;
    slcan_init(&rx);
    can_frame_t frame;
    uint8_t reply = 0u;
    push_text(&rx, "t1231AA\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a'); /* closed: refused */
    push_text(&rx, "S6\rO\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\r');
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\r' && rx.open);
    push_text(&rx, "t1231AA\r\nt4560\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_FRAME && frame.id == 0x123u && frame.data[0] == 0xAAu);
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_FRAME && frame.id == 0x456u && frame.len == 0u);
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_NONE);
    push_text(&rx, "t12"); /* half a line: nothing yet, the rest comes later */
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_NONE);
    push_text(&rx, "31BB\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_FRAME && frame.data[0] == 0xBBu);
    push_text(&rx, "Q\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a' && rx.bad_lines == 2u);
    push_text(&rx, "C\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\r' && !rx.open);
}

static void test_every_digit_outside_hex_is_refused(void)
{
    can_frame_t out;
    CHECK(!slcan_decode("t!231AA", 7u, &out));  /* below '0' */
    CHECK(!slcan_decode("t1:31AA", 7u, &out));  /* between '9' and 'A' */
    CHECK(!slcan_decode("t12g1AA", 7u, &out));  /* above 'f' */
    CHECK(!slcan_decode("t123-", 5u, &out));    /* a length that is no digit */
    CHECK(!slcan_decode("t8000", 5u, &out));    /* ID 0x800: above the standard range */
    CHECK(!slcan_decode("t1231#A", 7u, &out));  /* the high digit of a data byte */
    CHECK(!slcan_decode("t1231A#", 7u, &out));  /* the low digit */
    CHECK(slcan_decode("t7FF1fF", 7u, &out) && out.id == 0x7FFu && out.data[0] == 0xFFu);
}

static void test_every_known_command_is_answered_and_a_bad_frame_line_counted(void)
{
    static slcan_rx rx;
    slcan_init(&rx);
    can_frame_t frame;
    uint8_t reply = 0u;
    push_text(&rx, "L\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\r' && rx.open); /* listen-only */
    const char *accepted[] = {"s4037\r", "V\r", "v\r", "N\r", "F\r", "Z1\r"};
    for (unsigned i = 0; i < sizeof accepted / sizeof accepted[0]; ++i) {
        push_text(&rx, accepted[i]);
        CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\r');
    }
    push_text(&rx, "S1234567890123\r"); /* a command longer than any the adapter knows */
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a');
    push_text(&rx, "tXYZ0\r"); /* open, but not a frame */
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a' && rx.bad_lines == 1u);
}

static void test_an_overlong_line_is_dropped_whole(void)
{
    static slcan_rx rx;
    slcan_init(&rx);
    rx.open = true;
    can_frame_t frame;
    uint8_t reply = 0u;
    push_text(&rx, "t1238AABBCCDDEEFF0011223344556677\rt1231CC\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a');
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_FRAME && frame.data[0] == 0xCCu); /* the next is fine */
}

static void test_a_full_ring_counts_overflows_and_drops_the_damaged_line(void)
{
    static slcan_rx rx;
    slcan_init(&rx);
    rx.open = true;
    const uint32_t lines = SLCAN_RING_BYTES / SLCAN_FRAME_LINE; /* 23 whole lines fit in 512 bytes */
    for (uint32_t i = 0u; i < lines; ++i) {
        push_text(&rx, "t12380001020304050607\r");
    }
    CHECK(rx.overflows == 0u);
    push_text(&rx, "t1238AABBCCDDEEFF0011\r"); /* the main loop was busy: only its head fits */
    const uint32_t room = SLCAN_RING_BYTES - lines * SLCAN_FRAME_LINE;
    CHECK(rx.overflows == SLCAN_FRAME_LINE - room);
    can_frame_t frame;
    uint8_t reply = 0u;
    uint32_t frames = 0u;
    slcan_event event;
    while ((event = slcan_rx_poll(&rx, &frame, &reply)) == SLCAN_FRAME) {
        frames += 1u;
    }
    CHECK(frames == lines && event == SLCAN_NONE); /* the queued lines are intact; the cut one is pending */
    push_text(&rx, "\rt1231DD\r"); /* a terminator at last: the damaged line is dropped, not parsed */
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a' && rx.bad_lines == 1u);
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_FRAME && frame.data[0] == 0xDDu);
}

static void test_time_lines_carry_the_simulations_advance(void)
{
    static slcan_rx rx;
    slcan_init(&rx);
    can_frame_t frame;
    uint8_t reply = 0u;
    push_text(&rx, "Y493E0\rYFFFFFFFF\ry1\r");
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_TIME && rx.advance_us == 300000u);
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_TIME && rx.advance_us == 0xFFFFFFFFu);
    CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a'); /* lower case: not ours */
    push_text(&rx, "Y\rY123456789\rY12G\r"); /* no digits, nine digits, not hex: refused and counted */
    for (int i = 0; i < 3; ++i) {
        CHECK(slcan_rx_poll(&rx, &frame, &reply) == SLCAN_REPLY && reply == '\a');
    }
    CHECK(rx.bad_lines == 4u && rx.advance_us == 0xFFFFFFFFu); /* a refused line leaves the advance */
}

int main(void)
{
    test_encode_is_the_lawicel_line();
    test_decode_round_trips_every_length();
    test_corrupt_lines_are_refused();
    test_commands_open_the_channel_and_frames_pass_only_when_open();
    test_every_digit_outside_hex_is_refused();
    test_every_known_command_is_answered_and_a_bad_frame_line_counted();
    test_an_overlong_line_is_dropped_whole();
    test_a_full_ring_counts_overflows_and_drops_the_damaged_line();
    test_time_lines_carry_the_simulations_advance();
    printf("slcan: %d checks, %d failures\n", checks, failures);
    return failures == 0 ? 0 : 1;
}
