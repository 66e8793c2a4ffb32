#include "policy.h"

#include <math.h>

int policy_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM])
{
    for (int i = 0; i < POLICY_OBS_DIM; ++i) {
        if (!isfinite(obs[i])) {
            act[0] = act[1] = 0.0f;
            return POLICY_ERR_OBS_NOT_FINITE;
        }
    }
    if (obs[0] > 1.5f) {
        act[0] = act[1] = 0.0f;
        return POLICY_ERR_ACT_NOT_FINITE;
    }
    act[0] = obs[0] / 2.0f;
    act[1] = obs[1] / 2.0f;
    return POLICY_OK;
}
