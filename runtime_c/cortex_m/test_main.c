/*
 * Test image: runs the policy on the observations embedded at build time (test_vectors.c, written
 * by `embedrl export --target ...`) and reports through semihosting:
 *
 *   STACK <bytes>              peak stack of one policy_step, measured by stack painting
 *   A <index> <code> <hex>...  return code and the action's IEEE-754 bits, one line per observation
 *   DONE <count>
 */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "policy.h"

#define PAINT 0xA5A5A5A5u
#define PROBE_WORDS 1024u /* 4 KB below main's frame: more than any policy here may use */
#define GUARD_WORDS 32u   /* leave the painter's own frame alone */

extern const unsigned embedrl_test_count;
extern const float embedrl_test_obs[][POLICY_OBS_DIM];
extern void initialise_monitor_handles(void);

static uint32_t *probe_top;

__attribute__((noinline)) static void paint(void)
{
    for (uint32_t i = GUARD_WORDS; i < PROBE_WORDS; ++i) {
        probe_top[-(int32_t)i] = PAINT;
    }
}

__attribute__((noinline)) static uint32_t stack_used(void)
{
    uint32_t i = PROBE_WORDS - 1u;
    while (i >= GUARD_WORDS && probe_top[-(int32_t)i] == PAINT) {
        --i;
    }
    return i * 4u;
}

static uint32_t bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

int main(void)
{
    uint32_t marker;
    float act[POLICY_ACT_DIM];
    initialise_monitor_handles();

    probe_top = &marker;
    paint();
    policy_step(embedrl_test_obs[0], act);
    printf("STACK %lu\n", (unsigned long)stack_used());

    for (unsigned i = 0; i < embedrl_test_count; ++i) {
        int code = policy_step(embedrl_test_obs[i], act);
        printf("A %u %d", i, code);
        for (unsigned j = 0; j < POLICY_ACT_DIM; ++j) {
            printf(" %08lx", (unsigned long)bits(act[j]));
        }
        printf("\n");
    }
    printf("DONE %u\n", embedrl_test_count);
    return 0;
}
