/*
 * The node's CAN transport on bare metal (platform.h): CAN frames as SLCAN lines (slcan.h) over the board's
 * link UART (board.h).
 * Received bytes go into a ring buffer from the UART's receive interrupt, so a byte that arrives while
 * the policy runs is kept (or counted as an overflow when the ring is full); the main loop takes lines
 * out in transport_recv. The far end is a serial CAN adapter, or on the HIL bench python-can's `slcan`
 * interface bridged to the bus (hil/firmware.py).
 *
 * A time line (slcan.h) advances the node's clock (clock_advance_us) and ends transport_recv at once, so
 * that the node acts on the new time (its watchdog, its status frame); the "Y\r" answer goes out at the
 * next transport_recv, after whatever the node sent then: the harness, once it reads the answer, has every
 * frame the new time caused. A clock that takes no time from outside refuses the line ('\a').
 */
#include <stddef.h>

#include "board.h"
#include "platform.h"
#include "slcan.h"
#include "transport_uart.h"

static slcan_rx rx;
static uint32_t frame_ticks;
static uint32_t sent_ticks;
static const char *last_error = "not opened";

void LinkRx_Handler(void)
{
    board_link_rx_ack();
    while (board_link_rx_ready()) {
        slcan_rx_push(&rx, board_link_rx_byte());
    }
}

/* Sleep until a byte arrives, unless one already has: interrupts are masked from the ring's check to the
 * WFI, so a byte whose interrupt comes between the two is not slept through (its interrupt, pending, ends
 * the WFI and runs once they are unmasked). */
static void idle_until_byte(void)
{
    __asm__ volatile("cpsid i" ::: "memory");
    if (rx.head == rx.tail) {
        clock_idle();
    }
    __asm__ volatile("cpsie i" ::: "memory");
}


void diag_write(const char *text)
{
    for (size_t i = 0; text[i] != '\0'; ++i) {
        board_uart_put(true, (uint8_t)text[i]);
    }
}

int transport_open(const char *iface, const uint32_t *ids, unsigned count, int fd)
{
    (void)iface; /* one UART, and the IDs are checked by the node itself */
    (void)ids;
    (void)count;
    if (fd != 0) {
        last_error = "CAN FD frames cannot travel as classic SLCAN lines";
        return -1;
    }
    slcan_init(&rx);
    board_uarts_open();
    return 0;
}

void transport_await_open(void)
{
    while (!rx.open) {
        can_frame_t frame;
        uint8_t reply = 0u;
        slcan_event event = slcan_rx_poll(&rx, &frame, &reply);
        if (event == SLCAN_TIME) { /* answered at once: no node acts on the time yet */
            if (clock_advance_us(rx.advance_us)) {
                board_uart_put(false, (uint8_t)'Y');
                board_uart_put(false, (uint8_t)'\r');
            } else {
                board_uart_put(false, (uint8_t)'\a');
            }
        } else if (event == SLCAN_REPLY) {
            board_uart_put(false, reply);
        } else if (event == SLCAN_NONE) {
            idle_until_byte();
        } else {
            /* a frame: none is passed on before the channel opens */
        }
    }
}

transport_event transport_recv(can_frame_t *frame, uint8_t *bus_state, uint32_t timeout_ms)
{
    static bool time_answer_due; /* a time line taken: answered once the node has acted on it */
    (void)bus_state; /* a UART link has no controller error states */
    if (time_answer_due) {
        time_answer_due = false;
        board_uart_put(false, (uint8_t)'Y');
        board_uart_put(false, (uint8_t)'\r');
    }
    uint32_t start = clock_ms();
    do {
        uint8_t reply = 0u;
        slcan_event event = slcan_rx_poll(&rx, frame, &reply);
        if (event == SLCAN_FRAME) {
            frame_ticks = clock_ticks();
            return TRANSPORT_FRAME;
        }
        if (event == SLCAN_TIME) {
            if (clock_advance_us(rx.advance_us)) {
                time_answer_due = true;
                return TRANSPORT_TIMEOUT; /* the node's clock moved: let it act before the answer */
            }
            board_uart_put(false, (uint8_t)'\a');
        } else if (event == SLCAN_REPLY) {
            board_uart_put(false, reply);
        } else if (event == SLCAN_NONE) {
            idle_until_byte(); /* (or with the real-time clock, the next millisecond) */
        }
    } while ((uint32_t)(clock_ms() - start) < timeout_ms);
    return TRANSPORT_TIMEOUT;
}

int transport_send(const can_frame_t *frame)
{
    char line[SLCAN_MAX_LINE];
    uint32_t n = slcan_encode(frame, line);
    if (n == 0u || !rx.open) {
        return -1;
    }
    for (uint32_t i = 0u; (i + 1u) < n; ++i) {
        board_uart_put(false, (uint8_t)line[i]);
    }
    /* The last byte and the time it went, with interrupts masked: the far end may answer at once, and
     * its bytes' interrupt must not fall between the two (a step's instruction count ends here). */
    __asm__ volatile("cpsid i" ::: "memory");
    board_uart_put(false, (uint8_t)line[n - 1u]);
    sent_ticks = clock_ticks();
    __asm__ volatile("cpsie i" ::: "memory");
    return 0;
}

void transport_close(void)
{
    board_link_close();
}

const char *transport_error(void)
{
    return last_error;
}

uint32_t transport_frame_ticks(void)
{
    return frame_ticks;
}

uint32_t transport_sent_ticks(void)
{
    return sent_ticks;
}

uint32_t transport_overflows(void)
{
    return rx.overflows;
}

uint32_t transport_bad_lines(void)
{
    return rx.bad_lines;
}
