/* Test double of a generated policy (same contract as `embedrl export` output), for node unit tests. */
#ifndef POLICY_H
#define POLICY_H

#include <stdint.h>

#define POLICY_OBS_DIM 6u
#define POLICY_ACT_DIM 2u
#define POLICY_OK ((int32_t)0)
#define POLICY_ERR_OBS_NOT_FINITE ((int32_t)1)
#define POLICY_ERR_ACT_NOT_FINITE ((int32_t)2)
/* Not zero: the node's watchdog must send the policy's own safe action. */
#define POLICY_SAFE_ACTION {0.25f, -0.5f}

/* act = (obs[0] / 2, obs[1] / 2); if obs[0] > 1.5 the "network" overflows: safe action, code 2.
 * Two inputs make it lie, returning POLICY_OK with numbers the node must refuse: sin_theta (obs[2]) of
 * FAKE_POLICY_NAN_SIN gives act[0] = NaN, of FAKE_POLICY_OUT_OF_RANGE_SIN gives act[1] = -1.5. */
#define FAKE_POLICY_NAN_SIN 0.5f
#define FAKE_POLICY_OUT_OF_RANGE_SIN (-0.5f)
int32_t policy_step(const float obs[POLICY_OBS_DIM], float act[POLICY_ACT_DIM]);

/* Counts its calls in fake_policy_resets (the node resets a policy's memory at start-up and in SAFE). */
void policy_reset(void);
extern unsigned fake_policy_resets;

#endif
