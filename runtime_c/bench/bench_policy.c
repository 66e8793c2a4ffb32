/*
 * Timing harness for a generated policy (default name "policy").
 *
 *   bench_policy OBS_FILE REPEATS [ACTIONS_FILE]
 *
 * OBS_FILE holds N observations as raw little-endian float32, POLICY_OBS_DIM per row. The harness
 * runs policy_step once per observation, REPEATS times over the file, and prints the median over
 * the repeats of the nanoseconds per single-observation inference, and a checksum of the actions
 * (so the calls cannot be optimised away); then the same for policy_step_batch on the whole file
 * (ns_per_observation_batched). ACTIONS_FILE: the actions of every observation, raw float32.
 *
 * Built with -DPEER (make bench-peer PEER_C=...), it times another generator's C of the same policy
 * instead, emx-onnx-cgen's, whose entry point `peer(batch, obs, act)` takes one row or the whole file.
 */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#if defined(PEER) || defined(POLICY_WITHOUT_HOST_FILE)
#include "policy.h" /* an export from before the host file declares policy_step_batch here */
#else
#include "policy_host.h" /* policy_step, and the host-only policy_step_batch */
#endif

#if defined(PEER)
void peer(int batch, const float obs[][POLICY_OBS_DIM], float act[][POLICY_ACT_DIM]);
#define STEP_ONE(obs, act) peer(1, (const float(*)[POLICY_OBS_DIM])(obs), (float(*)[POLICY_ACT_DIM])(act))
#define STEP_ALL(n, obs, act) peer((n), (obs), (act))
#else
#define STEP_ONE(obs, act) policy_step((obs), (act))
#define STEP_ALL(n, obs, act) policy_step_batch((n), &(obs)[0][0], &(act)[0][0], NULL)
#endif

#define MAX_OBS 20000
#define MAX_REPEATS 101

static float observations[MAX_OBS][POLICY_OBS_DIM];
static float actions[MAX_OBS][POLICY_ACT_DIM];

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e9 + (double)t.tv_nsec;
}

static int compare(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv)
{
    if (argc != 3 && argc != 4) {
        fprintf(stderr, "usage: %s OBS_FILE REPEATS [ACTIONS_FILE]\n", argv[0]);
        return 2;
    }
    FILE *f = fopen(argv[1], "rb");
    if (f == NULL) {
        fprintf(stderr, "cannot open %s\n", argv[1]);
        return 2;
    }
    size_t n = fread(observations, sizeof(float) * POLICY_OBS_DIM, MAX_OBS, f);
    fclose(f);
    int repeats = atoi(argv[2]);
    if (n == 0 || repeats < 1 || repeats > MAX_REPEATS) {
        fprintf(stderr, "need 1..%d observations and 1..%d repeats\n", MAX_OBS, MAX_REPEATS);
        return 2;
    }
    double per_call[MAX_REPEATS];
    double checksum = 0.0;
    float act[POLICY_ACT_DIM];
    for (int r = 0; r < repeats; ++r) {
        double start = now_ns();
        for (size_t i = 0; i < n; ++i) {
            STEP_ONE(observations[i], act);
            checksum += (double)act[0];
        }
        per_call[r] = (now_ns() - start) / (double)n;
    }
    qsort(per_call, (size_t)repeats, sizeof(double), compare);
    printf("ns_per_inference %.1f\nchecksum %.6f\nobservations %zu\n", per_call[repeats / 2], checksum, n);
    double batch_checksum = 0.0;
    for (int r = 0; r < repeats; ++r) {
        double start = now_ns();
        STEP_ALL((int)n, observations, actions);
        per_call[r] = (now_ns() - start) / (double)n;
        batch_checksum += (double)actions[n - 1][0];
    }
    qsort(per_call, (size_t)repeats, sizeof(double), compare);
    printf("ns_per_observation_batched %.1f\nbatch_checksum %.6f\n", per_call[repeats / 2], batch_checksum);
    if (argc == 4) {
        for (size_t i = 0; i < n; ++i) {
            STEP_ONE(observations[i], actions[i]);
        }
        FILE *out = fopen(argv[3], "wb");
        if (out == NULL || fwrite(actions, sizeof(float) * POLICY_ACT_DIM, n, out) != n) {
            fprintf(stderr, "cannot write %s\n", argv[3]);
            return 2;
        }
        fclose(out);
    }
    return 0;
}
