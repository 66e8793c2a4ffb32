/*
 * The board file of ARM's MPS2 FPGA images (QEMU's mps2-an385/an386/an500): CMSDK APB UARTs and timers at
 * their documented addresses, the Cortex-M NVIC. The node's platform files (transport_uart.c, timer.c,
 * clock_*.c) and the test images reach the peripherals only through the functions below; another part has
 * its own board file with the same functions (boards/<board>/board.h, picked by targets.mk's BOARD).
 */
#ifndef EMBEDRL_BOARD_H
#define EMBEDRL_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#include "board_common.h"

#define BOARD_REG(addr) (*(volatile uint32_t *)(addr))

#define BOARD_PCLK_HZ 25000000u  /* the APB clock of the MPS2 images: UART baud and TIMER0 tick */
#define BOARD_TIMER_HZ BOARD_PCLK_HZ
#define BOARD_TIMER_MASK 0xFFFFFFFFu /* a 32-bit counter: tick differences wrap at 2^32 */
#define BOARD_CPU_HZ 25000000u   /* the processor clock (SysTick) */

/* CMSDK APB UART: DATA, STATE (bit 0 TX full, bit 1 RX full), CTRL (TX, RX, TX irq, RX irq enables),
 * INTSTATUS (write 1 to clear), BAUDDIV. */
#define UART0_BASE 0x40004000u /* the CAN link (SLCAN) */
#define UART1_BASE 0x40005000u /* the diagnostics line (per-step instruction counts) */
#define UART_DATA(b) BOARD_REG((b) + 0x00u)
#define UART_STATE(b) BOARD_REG((b) + 0x04u)
#define UART_CTRL(b) BOARD_REG((b) + 0x08u)
#define UART_INTSTATUS(b) BOARD_REG((b) + 0x0Cu)
#define UART_BAUDDIV(b) BOARD_REG((b) + 0x10u)
#define UART_STATE_TX_FULL 0x1u
#define UART_STATE_RX_FULL 0x2u
#define UART_CTRL_TX 0x1u
#define UART_CTRL_RX 0x2u
#define UART_CTRL_RX_IRQ 0x8u
#define UART_INT_RX 0x2u
#define UART_BAUDDIV_MIN 16u /* the fastest rate the CMSDK UART accepts: PCLK / 16 */
#define BOARD_LINK_IRQ 0u    /* NVIC line of UART0's receive interrupt */

/* CMSDK APB timer: a 32-bit down counter at BOARD_PCLK_HZ. */
#define TIMER0_BASE 0x40000000u
#define TIMER_CTRL(b) BOARD_REG((b) + 0x00u)
#define TIMER_VALUE(b) BOARD_REG((b) + 0x04u)
#define TIMER_RELOAD(b) BOARD_REG((b) + 0x08u)
#define TIMER_CTRL_ENABLE 0x1u

#define NVIC_ISER0 BOARD_REG(0xE000E100u)

/* The link and diagnostics UARTs at their fastest rate; the link's receive interrupt enabled. */
static inline void board_uarts_open(void)
{
    UART_BAUDDIV(UART0_BASE) = UART_BAUDDIV_MIN;
    UART_BAUDDIV(UART1_BASE) = UART_BAUDDIV_MIN;
    UART_CTRL(UART1_BASE) = UART_CTRL_TX;
    UART_CTRL(UART0_BASE) = UART_CTRL_TX | UART_CTRL_RX | UART_CTRL_RX_IRQ;
    NVIC_ISER0 = 1u << BOARD_LINK_IRQ;
}

static inline void board_link_close(void)
{
    UART_CTRL(UART0_BASE) = 0u;
}

/* Write one byte to the link (diag false) or the diagnostics UART (diag true), waiting for room. */
static inline void board_uart_put(bool diag, uint8_t byte)
{
    uint32_t base = diag ? UART1_BASE : UART0_BASE;
    while ((UART_STATE(base) & UART_STATE_TX_FULL) != 0u) {
    }
    UART_DATA(base) = byte;
}

/* In the link's receive interrupt: acknowledge it; then take bytes while board_link_rx_ready. */
static inline void board_link_rx_ack(void)
{
    UART_INTSTATUS(UART0_BASE) = UART_INT_RX;
}

static inline bool board_link_rx_ready(void)
{
    return (UART_STATE(UART0_BASE) & UART_STATE_RX_FULL) != 0u;
}

static inline uint8_t board_link_rx_byte(void)
{
    return (uint8_t)(UART_DATA(UART0_BASE) & 0xFFu);
}

/* The free-running timer from 0: board_timer_ticks counts up at BOARD_TIMER_HZ, wrapping at 2^32. */
static inline void board_timer_start(void)
{
    TIMER_RELOAD(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_VALUE(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_CTRL(TIMER0_BASE) = TIMER_CTRL_ENABLE;
}

static inline uint32_t board_timer_ticks(void)
{
    return 0xFFFFFFFFu - TIMER_VALUE(TIMER0_BASE); /* a down counter */
}

#endif /* EMBEDRL_BOARD_H */
