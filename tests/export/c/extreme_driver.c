/* Reads float32 observations (POLICY_OBS_DIM per record) on stdin until EOF; for each writes the return
 * code (int32) and the action (POLICY_ACT_DIM float32) on stdout. Built with -fsanitize=undefined,address
 * -fno-sanitize-recover=all by tests/export/test_extreme_inputs.py. */
#include <stdint.h>
#include <stdio.h>

#include "policy.h"

int main(void)
{
    float obs[POLICY_OBS_DIM];
    float act[POLICY_ACT_DIM];
    while (fread(obs, sizeof obs, 1, stdin) == 1) {
        int32_t code = (int32_t)policy_step(obs, act);
        if (fwrite(&code, sizeof code, 1, stdout) != 1 || fwrite(act, sizeof act, 1, stdout) != 1) {
            return 3;
        }
    }
    return 0;
}
