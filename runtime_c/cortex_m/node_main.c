/*
 * The policy node as firmware: the same node.c as the host's policy_node, on the board's UART (CAN frames
 * as SLCAN lines, transport_uart.c) and timer (clock_timer.c). The same loop as node/main.c; the
 * configuration is fixed at build time (NODE_TIMEOUT_MS, NODE_RECOVER, NODE_ID; make variables).
 *
 * Diagnostics line (UART1), one line each:
 *   LINK                        the link's UART is enabled: the far end may open the channel
 *   READY                       the node runs (after the far end opened the channel)
 *   S <step> <cycle>            a step answered: timer ticks from its observation's last frame in to the
 *                               end of the last frame it sent (its action; under QEMU -icount: instructions,
 *                               see timer.c)
 *   X <overflows> <bad_lines> <stack>
 *                               after each status frame: receive-ring overflows, refused lines and the
 *                               peak stack so far in bytes (the stack is painted at start: every word
 *                               below main's frame that no longer holds the paint was used, interrupts
 *                               included)
 */
#include "board.h"
#include "node.h"
#include "transport_uart.h"

#ifndef NODE_TIMEOUT_MS
#define NODE_TIMEOUT_MS POLICY_IO_WATCHDOG_MS
#endif
#ifndef NODE_RECOVER
#define NODE_RECOVER 3u
#endif
#ifndef NODE_ID
#define NODE_ID 0u
#endif

#define DECIMAL_DIGITS 11u
#define PAINT 0xA5A5A5A5u

extern uint32_t _sstack[], _estack[];

/* Paint from the stack's bottom up to just below this frame; volatile so that gcc does not turn the loop
 * into a memset call, whose own frame would sit in the painted area. */
static void paint_stack(void)
{
    uint32_t *sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    for (volatile uint32_t *word = _sstack; word < sp - 1; ++word) {
        *word = PAINT;
    }
}

/* Bytes from the top of RAM down to the lowest word that lost its paint. */
static uint32_t stack_peak(void)
{
    const volatile uint32_t *word = _sstack;
    while (word < _estack && *word == PAINT) {
        ++word;
    }
    return (uint32_t)((uintptr_t)_estack - (uintptr_t)word);
}

static void diag_u32(uint32_t value)
{
    char text[DECIMAL_DIGITS + 1u];
    uint32_t n = DECIMAL_DIGITS;
    text[n] = '\0';
    do {
        text[--n] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value != 0u && n > 0u);
    diag_write(&text[n]);
}

static void report_step(uint32_t step, uint32_t cycle_ticks)
{
    diag_write("S ");
    diag_u32(step);
    diag_write(" ");
    diag_u32(cycle_ticks);
    diag_write("\n");
}

int main(void)
{
    paint_stack();
    clock_init();
    const node_config config = {NODE_TIMEOUT_MS, NODE_RECOVER, POLICY_IO_STATUS_PERIOD_MS, NODE_ID};
    uint32_t ids[NODE_RX_IDS];
    node_receive_ids(config.node_id, ids);
    if (transport_open("uart0", ids, NODE_RX_IDS, POLICY_IO_FD) != 0) {
        diag_write("E ");
        diag_write(transport_error());
        diag_write("\n");
        return 1;
    }
    diag_write("LINK\n");
    transport_await_open(); /* the node's first status goes out once it can reach the bus */
    static node_t node;
    node_init(&node, &config, clock_ms());
    diag_write("READY\n");
    uint32_t status_counter = node.status_counter;
    for (;;) {
        uint32_t wait_ms = node_poll(&node, clock_ms());
        can_frame_t frame;
        uint8_t bus_state = 0u;
        if (transport_recv(&frame, &bus_state, wait_ms) == TRANSPORT_FRAME) {
            uint32_t answered = node.actions_sent;
            node_on_frame(&node, &frame, clock_ms());
            if (node.actions_sent != answered) {
                uint32_t cycle = (transport_sent_ticks() - transport_frame_ticks()) & BOARD_TIMER_MASK; /* the last frame sent */
                report_step(node.last_step, cycle);
            }
        }
        if (node.status_counter != status_counter) {
            status_counter = node.status_counter;
            diag_write("X ");
            diag_u32(transport_overflows());
            diag_write(" ");
            diag_u32(transport_bad_lines());
            diag_write(" ");
            diag_u32(stack_peak());
            diag_write("\n");
        }
    }
}
