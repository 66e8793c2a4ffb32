/*
 * The node's clock in the simulation's time (platform.h), for processor-in-the-loop runs: the harness
 * sends a time line ("Y" and the microseconds, slcan.h) before each step's observation and while it lets
 * the bus stay quiet, and the clock advances only by those lines. The watchdog and the status period then
 * count simulated time: a host too slow or too busy to keep up delays the whole simulation, node
 * included, and never looks like a silent bus; a bus the simulation silences (fault injection) trips the
 * watchdog after exactly its timeout of simulated time.
 *
 * No SysTick interrupt: the idle loop's WFI ends on a received byte only, so nothing interrupts a step
 * and its instruction count (timer.c) is the same on every run. The time the node spends computing is
 * not added (a step is ~50 us at the part's clock, under 0.1 % of a sample time); clock_us therefore
 * reads 0 for a step's inference, whose cost is the instruction count instead.
 */
#include "board.h"
#include "platform.h"

#define US_PER_MS 1000u

static uint64_t now_us;

void clock_init(void)
{
    timer_start();
    now_us = 0u;
}

bool clock_advance_us(uint32_t us)
{
    now_us += us;
    return true;
}

uint32_t clock_us(void)
{
    return (uint32_t)now_us;
}

uint32_t clock_ms(void)
{
    return (uint32_t)(now_us / US_PER_MS);
}

void sleep_ms(uint32_t ms)
{
    (void)ms; /* simulated time passes only by the harness's time lines: nothing to wait for here */
}
