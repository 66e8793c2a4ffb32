/*
 * The board's free-running timer and the idle instruction, shared by both clocks (clock_timer.c,
 * clock_sim.c): TIMER0 counts down at BOARD_PCLK_HZ from 2^32 - 1; clock_ticks counts up from timer_start.
 * Under QEMU with -icount shift=N a tick is 40 / 2^N guest instructions (40 at shift=0) while the core
 * runs: the node's per-step instruction counts (node_main.c) are tick differences with no idle in between.
 */
#include "board.h"

void timer_start(void)
{
    TIMER_RELOAD(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_VALUE(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_CTRL(TIMER0_BASE) = TIMER_CTRL_ENABLE;
}

uint32_t clock_ticks(void)
{
    return 0xFFFFFFFFu - TIMER_VALUE(TIMER0_BASE);
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
