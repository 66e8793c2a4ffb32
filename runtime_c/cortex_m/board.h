/*
 * The emulated board's peripherals (QEMU's mps2-an385/an386/an500, ARM's MPS2 FPGA images): CMSDK APB
 * UARTs and timers at their documented addresses, the Cortex-M NVIC. A real part maps its own UART and
 * timer behind the same functions (transport_uart.c, clock_timer.c): only these addresses change.
 */
#ifndef EMBEDRL_BOARD_H
#define EMBEDRL_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#define BOARD_REG(addr) (*(volatile uint32_t *)(addr))

#define BOARD_PCLK_HZ 25000000u /* the APB clock of the MPS2 images: UART baud and TIMER0 tick */

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
#define UART0_RX_IRQ 0u /* NVIC line of UART0's receive interrupt */

/* CMSDK APB timer: a 32-bit down counter at BOARD_PCLK_HZ. */
#define TIMER0_BASE 0x40000000u
#define TIMER_CTRL(b) BOARD_REG((b) + 0x00u)
#define TIMER_VALUE(b) BOARD_REG((b) + 0x04u)
#define TIMER_RELOAD(b) BOARD_REG((b) + 0x08u)
#define TIMER_CTRL_ENABLE 0x1u

#define NVIC_ISER0 BOARD_REG(0xE000E100u)

/* SysTick (processor clock, 25 MHz on the MPS2 images): a 1 ms interrupt wakes the idle loop's WFI. */
#define SYST_CSR BOARD_REG(0xE000E010u)
#define SYST_RVR BOARD_REG(0xE000E014u)
#define SYST_CVR BOARD_REG(0xE000E018u)
#define SYST_CSR_ENABLE_TICKINT_CORE 0x7u
#define BOARD_CPU_HZ 25000000u

/* The free-running timer (timer.c): started by clock_init; ticks since then (wraps after 2^32 ticks: 171 s
 * at 25 MHz). */
void timer_start(void);
uint32_t clock_ticks(void);
/* Sleep until the next interrupt (a received byte, or with the real-time clock the next millisecond); an
 * interrupt already pending, even masked, ends it at once. */
void clock_idle(void);

/* The node's clock, one of two picked at link time (make NODE_CLOCK=sim|timer): clock_sim.c (the
 * simulation's time, from the harness's time lines) or clock_timer.c (real time, SysTick every 1 ms). */
void clock_init(void);
/* The simulation's time advanced by us microseconds: true if this clock takes it (clock_sim.c). */
bool clock_advance_us(uint32_t us);
void SysTick_Handler(void);

/* Write bytes to the diagnostics UART (blocking). */
void diag_write(const char *text);

#endif /* EMBEDRL_BOARD_H */
