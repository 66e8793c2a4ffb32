/*
 * Size probe: with POLICY defined the image calls policy_step once, without it not at all. The
 * difference between the two linked images is what the policy costs: its code, weights and
 * buffers plus every library routine it pulls in (libm, soft-float helpers).
 */
#define PROBE_IO 8 /* both images carry the same volatile buffer, so it cancels in the difference */

static volatile float io[PROBE_IO];

#if defined(POLICY)
#include "policy.h"

int main(void)
{
    float obs[POLICY_OBS_DIM];
    float act[POLICY_ACT_DIM];
    for (unsigned i = 0; i < POLICY_OBS_DIM; ++i) {
        obs[i] = io[i % PROBE_IO];
    }
    int32_t code = policy_step(obs, act);
    for (unsigned i = 0; i < POLICY_ACT_DIM; ++i) {
        io[i % PROBE_IO] = act[i];
    }
    return (int)code;
}
#else
int main(void)
{
    io[0] = io[1];
    return 0;
}
#endif
