/* Monotonic clock for Linux hosts. */
#define _POSIX_C_SOURCE 199309L
#include <time.h>

#include "platform.h"

static struct timespec now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t;
}

uint32_t clock_ms(void)
{
    struct timespec t = now();
    return (uint32_t)((uint64_t)t.tv_sec * 1000u + (uint64_t)t.tv_nsec / 1000000u);
}

uint32_t clock_us(void)
{
    struct timespec t = now();
    return (uint32_t)((uint64_t)t.tv_sec * 1000000u + (uint64_t)t.tv_nsec / 1000u);
}

void sleep_ms(uint32_t ms)
{
    struct timespec t = {(time_t)(ms / 1000u), (long)(ms % 1000u) * 1000000L};
    while (nanosleep(&t, &t) != 0) {
    }
}
