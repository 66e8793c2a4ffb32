/*
 * Peer image: another code generator's C of the same policy (emx-onnx-cgen's, whose entry point is
 * `void peer(int batch, const float obs[batch][OBS], float act[batch][ACT])`), timed as the test image
 * times policy_step (export/cycles.py):
 *
 *   A <index> <hex>...           the action's IEEE-754 bits, one line per observation
 *   TICKS <peer> <empty> <count> timer ticks (board.h) of a loop calling it on every observation, and of the same
 *                                loop around a function that does nothing
 *
 * With PROBE defined it only calls the peer once (the image traced for the cycle estimate).
 */
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include "board.h"
#include "policy.h" /* POLICY_OBS_DIM, POLICY_ACT_DIM: the export's dimensions */

void peer(int batch, const float obs[][POLICY_OBS_DIM], float act[][POLICY_ACT_DIM]);

extern const unsigned embedrl_test_count;
extern const float embedrl_test_obs[][POLICY_OBS_DIM];
extern void initialise_monitor_handles(void);

typedef void (*peer_fn)(int, const float[][POLICY_OBS_DIM], float[][POLICY_ACT_DIM]);

static void __attribute__((noinline)) no_peer(int batch, const float obs[][POLICY_OBS_DIM], float act[][POLICY_ACT_DIM])
{
    __asm__ volatile("" : : "r"(batch), "r"(obs), "r"(act) : "memory");
}

static uint32_t timed_pass(volatile peer_fn fn, float act[1][POLICY_ACT_DIM])
{
    uint32_t start = board_timer_ticks();
    for (unsigned i = 0; i < embedrl_test_count; ++i) {
        fn(1, &embedrl_test_obs[i], act);
    }
    return (board_timer_ticks() - start) & BOARD_TIMER_MASK;
}

int main(void)
{
    float act[1][POLICY_ACT_DIM];
#if defined(PROBE)
    peer(1, &embedrl_test_obs[0], act);
    return act[0][0] != act[0][0]; /* uses the result */
#else
    initialise_monitor_handles();
    for (unsigned i = 0; i < embedrl_test_count; ++i) {
        peer(1, &embedrl_test_obs[i], act);
        printf("A %u", i);
        for (unsigned j = 0; j < POLICY_ACT_DIM; ++j) {
            uint32_t bits;
            memcpy(&bits, &act[0][j], sizeof bits);
            printf(" %08lx", (unsigned long)bits);
        }
        printf("\n");
    }
    board_timer_start();
    uint32_t peer_ticks = timed_pass(peer, act);
    uint32_t empty_ticks = timed_pass(no_peer, act);
    printf("TICKS %lu %lu %u\n", (unsigned long)peer_ticks, (unsigned long)empty_ticks, embedrl_test_count);
    printf("DONE %u\n", embedrl_test_count);
    return 0;
#endif
}
