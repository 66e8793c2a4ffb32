/*
 * The node's CAN transport on bare metal (platform.h): CAN frames as SLCAN lines (slcan.h) over UART0.
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

#define UART_BAUDDIV_MIN 16u /* the fastest rate the CMSDK UART accepts: PCLK / 16 */

static slcan_rx rx;
static uint32_t frame_ticks;
static const char *last_error = "not opened";

void UART0RX_Handler(void)
{
    UART_INTSTATUS(UART0_BASE) = UART_INT_RX;
    while (UART_STATE(UART0_BASE) & UART_STATE_RX_FULL) {
        slcan_rx_push(&rx, (uint8_t)(UART_DATA(UART0_BASE) & 0xFFu));
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

static void uart_put(uint32_t base, uint8_t byte)
{
    while (UART_STATE(base) & UART_STATE_TX_FULL) {
    }
    UART_DATA(base) = byte;
}

void diag_write(const char *text)
{
    for (size_t i = 0; text[i] != '\0'; ++i) {
        uart_put(UART1_BASE, (uint8_t)text[i]);
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
    UART_BAUDDIV(UART0_BASE) = UART_BAUDDIV_MIN;
    UART_BAUDDIV(UART1_BASE) = UART_BAUDDIV_MIN;
    UART_CTRL(UART1_BASE) = UART_CTRL_TX;
    UART_CTRL(UART0_BASE) = UART_CTRL_TX | UART_CTRL_RX | UART_CTRL_RX_IRQ;
    NVIC_ISER0 = 1u << UART0_RX_IRQ;
    return 0;
}

transport_event transport_recv(can_frame_t *frame, uint8_t *bus_state, uint32_t timeout_ms)
{
    static bool time_answer_due; /* a time line taken: answered once the node has acted on it */
    (void)bus_state; /* a UART link has no controller error states */
    if (time_answer_due) {
        time_answer_due = false;
        uart_put(UART0_BASE, (uint8_t)'Y');
        uart_put(UART0_BASE, (uint8_t)'\r');
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
            uart_put(UART0_BASE, (uint8_t)'\a');
        } else if (event == SLCAN_REPLY) {
            uart_put(UART0_BASE, reply);
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
    for (uint32_t i = 0u; i < n; ++i) {
        uart_put(UART0_BASE, (uint8_t)line[i]);
    }
    return 0;
}

void transport_close(void)
{
    UART_CTRL(UART0_BASE) = 0u;
}

const char *transport_error(void)
{
    return last_error;
}

uint32_t transport_frame_ticks(void)
{
    return frame_ticks;
}

uint32_t transport_overflows(void)
{
    return rx.overflows;
}

uint32_t transport_bad_lines(void)
{
    return rx.bad_lines;
}
