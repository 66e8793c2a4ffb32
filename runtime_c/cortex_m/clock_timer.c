/*
 * The node's clock on bare metal (platform.h): TIMER0 counts down at BOARD_PCLK_HZ; clock_ms and
 * clock_us extend it past its 32-bit wrap in 64 bits (the node reads the clock at least every
 * watchdog period, far more often than the 171 s wrap).
 *
 * Under QEMU with -icount shift=N, virtual time advances 2^N ns per guest instruction, so a tick is
 * 40 / 2^N instructions (40 at shift=0): the harness turns tick counts into instruction counts. While the
 * core sleeps in WFI (clock_idle), QEMU's virtual time follows the host's, so the watchdog and the status
 * period run in real time between steps.
 */
#include "board.h"
#include "platform.h"

#define TICKS_PER_US (BOARD_PCLK_HZ / 1000000u)

static uint32_t last_ticks;
static uint64_t total_ticks;

void clock_init(void)
{
    TIMER_RELOAD(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_VALUE(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_CTRL(TIMER0_BASE) = TIMER_CTRL_ENABLE;
    last_ticks = 0u;
    total_ticks = 0u;
    SYST_RVR = BOARD_CPU_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = SYST_CSR_ENABLE_TICKINT_CORE;
}

void SysTick_Handler(void)
{
    /* nothing to do: the interrupt only ends the idle loop's WFI */
}

void clock_idle(void)
{
    __asm__ volatile("wfi" ::: "memory");
}

uint32_t clock_ticks(void)
{
    return 0xFFFFFFFFu - TIMER_VALUE(TIMER0_BASE);
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
