#include "policy.h"

#include <math.h>

static const float safe_action[POLICY_ACT_DIM] = POLICY_SAFE_ACTION;

unsigned fake_policy_resets = 0;

void policy_reset(void)
{
    fake_policy_resets++;
}

static int32_t safe(float act[POLICY_ACT_DIM], int32_t code)
{
    act[0] = safe_action[0];
    act[1] = safe_action[1];
    return code;
}

int32_t policy_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM])
{
    for (uint32_t i = 0u; i < POLICY_OBS_DIM; ++i) {
        if (!isfinite(obs[i])) {
            return safe(act, POLICY_ERR_OBS_NOT_FINITE);
        }
    }
    if (obs[0] > 1.5f) {
        return safe(act, POLICY_ERR_ACT_NOT_FINITE);
    }
    if (obs[2] == FAKE_POLICY_NAN_SIN) { /* a policy that lies: NaN with status OK */
        act[0] = NAN;
        act[1] = 0.0f;
        return POLICY_OK;
    }
    if (obs[2] == FAKE_POLICY_OUT_OF_RANGE_SIN) { /* status OK, an action beyond the interface's range */
        act[0] = 0.0f;
        act[1] = -1.5f;
        return POLICY_OK;
    }
    act[0] = obs[0] / 2.0f;
    act[1] = obs[1] / 2.0f;
    return POLICY_OK;
}
