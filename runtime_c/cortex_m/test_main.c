/*
 * Test image: runs the policy on the observations embedded at build time (test_vectors.c, written
 * by `embedrl export --target ...`) and reports through semihosting:
 *
 *   STACK <bytes>              peak stack of one policy_step, measured by stack painting
 *   A <index> <code> <hex>...  return code and the action's IEEE-754 bits, one line per observation
 *   TICKS <policy> <empty> <count>
 *                              timer ticks (board.h) of a loop calling policy_step on every observation, and of the
 *                              same loop calling a function that does nothing (the loop's own cost);
 *                              under QEMU -icount shift=0 a tick is targets.mk's TICK instructions
 *   DONE <count>
 */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "board.h"
#include "policy.h"

#define PAINT 0xA5A5A5A5u

extern const unsigned embedrl_test_count;
extern const float embedrl_test_obs[][POLICY_OBS_DIM];
extern void initialise_monitor_handles(void);
extern uint32_t _sstack[]; /* the bottom of the stack reservation (sections.ld) */

static int32_t __attribute__((noinline)) no_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM])
{
    __asm__ volatile("" : : "r"(obs), "r"(act) : "memory");
    return 0;
}

/* Ticks of one pass over the observations calling step (through a volatile pointer: the same call). */
static uint32_t timed_pass(int32_t (*volatile step)(const float *, float *), float act[POLICY_ACT_DIM])
{
    uint32_t start = board_timer_ticks();
    for (unsigned i = 0; i < embedrl_test_count; ++i) {
        (void)step(embedrl_test_obs[i], act);
    }
    return (board_timer_ticks() - start) & BOARD_TIMER_MASK;
}

static uint32_t bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

int main(void)
{
    float act[POLICY_ACT_DIM];
    initialise_monitor_handles();

    /* Stack painting, all inside main so that no other frame lives below its stack pointer while
     * painting and scanning: everything policy_step (and what it calls) writes below it is its use. */
    uint32_t *top;
    __asm__ volatile("mov %0, sp" : "=r"(top));
    volatile uint32_t *sp = top; /* volatile: gcc must not turn the loop into a memset call, whose own
                                    frame would sit in the painted area */
    const uint32_t probe_words = (uint32_t)(top - _sstack); /* down to the reservation's bottom, no further */
    for (uint32_t i = 1; i <= probe_words; ++i) {
        sp[-(int32_t)i] = PAINT;
    }
    policy_step(embedrl_test_obs[0], act);
    uint32_t used = probe_words;
    while (used > 0 && sp[-(int32_t)used] == PAINT) {
        --used;
    }
    printf("STACK %lu\n", (unsigned long)(used * 4u));

    policy_reset(); /* a recurrent policy answers the vectors as one sequence from zero state */
    for (unsigned i = 0; i < embedrl_test_count; ++i) {
        int32_t code = policy_step(embedrl_test_obs[i], act);
        printf("A %u %ld", i, (long)code);
        for (unsigned j = 0; j < POLICY_ACT_DIM; ++j) {
            printf(" %08lx", (unsigned long)bits(act[j]));
        }
        printf("\n");
    }
    board_timer_start();
    uint32_t policy_ticks = timed_pass(policy_step, act);
    uint32_t empty_ticks = timed_pass(no_step, act);
    printf("TICKS %lu %lu %u\n", (unsigned long)policy_ticks, (unsigned long)empty_ticks, embedrl_test_count);
    printf("DONE %u\n", embedrl_test_count);
    return 0;
}
