/*
 * The node's clock in real time (platform.h), for a part on its own: the board's timer (timer.c),
 * extended past its 32-bit wrap in 64 bits (the node reads the clock at least every watchdog period, far
 * more often than the timer's wrap), and a 1 ms SysTick interrupt that wakes the idle loop's WFI.
 *
 * Under QEMU, while the core sleeps in WFI, virtual time follows the host's, so the watchdog and the
 * status period run in host time: a slow harness looks like a silent bus. Processor-in-the-loop runs use
 * the simulation's time instead (clock_sim.c).
 */
#include "board.h"
#include "platform.h"

#if defined(BOARD_TIMER_IS_SYSTICK)
#error "NODE_CLOCK=timer needs a timer besides SysTick (its 1 ms interrupt): this board's timer is SysTick; use NODE_CLOCK=sim"
#endif

#define TICKS_PER_US (BOARD_TIMER_HZ / 1000000u)

static uint32_t last_ticks;
static uint64_t total_ticks;

void clock_init(void)
{
    timer_start();
    last_ticks = 0u;
    total_ticks = 0u;
    SYST_RVR = BOARD_CPU_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = SYST_CSR_ENABLE_TICKINT_CORE;
}

bool clock_advance_us(uint32_t us)
{
    (void)us;
    return false; /* a real-time clock takes no time from outside */
}

static uint64_t ticks64(void)
{
    uint32_t now = clock_ticks();
    total_ticks += (uint32_t)(now - last_ticks);
    last_ticks = now;
    return total_ticks;
}

uint32_t clock_us(void)
{
    return (uint32_t)(ticks64() / TICKS_PER_US);
}

uint32_t clock_ms(void)
{
    return (uint32_t)(ticks64() / (TICKS_PER_US * 1000u));
}

void sleep_ms(uint32_t ms)
{
    uint32_t start = clock_ms();
    while ((uint32_t)(clock_ms() - start) < ms) {
    }
}
