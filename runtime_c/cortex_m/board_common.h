/*
 * What every board file (boards/<board>/board.h) shares: the Cortex-M core's SysTick, and the node's
 * clock and diagnostics functions built on the board's peripherals. Included by the board file.
 */
#ifndef EMBEDRL_BOARD_COMMON_H
#define EMBEDRL_BOARD_COMMON_H

#include <stdbool.h>
#include <stdint.h>

/* SysTick (the processor clock): with the real-time clock, a 1 ms interrupt wakes the idle loop's WFI. */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define SYST_CSR_ENABLE_TICKINT_CORE 0x7u

/* The free-running timer (timer.c): started by clock_init; ticks since then (board_timer_ticks), modulo
 * BOARD_TIMER_MASK + 1 (the board's counter width): differences are taken with the mask. */
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

#endif /* EMBEDRL_BOARD_COMMON_H */
