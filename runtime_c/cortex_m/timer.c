/*
 * The board's free-running timer and the idle instruction, shared by both clocks (clock_timer.c,
 * clock_sim.c): clock_ticks counts up from timer_start (board_timer_ticks). Under QEMU with -icount
 * shift=0 a tick is a fixed number of guest instructions while the core runs (targets.mk's TICK): the
 * node's per-step instruction counts (node_main.c) are tick differences with no idle in between.
 */
#include "board.h"

void timer_start(void)
{
    board_timer_start();
}

uint32_t clock_ticks(void)
{
    return board_timer_ticks();
}

void clock_idle(void)
{
    __asm__ volatile("wfi" ::: "memory");
}

void SysTick_Handler(void)
{
    /* nothing to do: the interrupt only ends the idle loop's WFI (the real-time clock enables it every
     * 1 ms; the simulated clock never does) */
}
