/*
 * Coverage driver of a generated policy (make coverage): runs the policy over the observations in the file
 * named by its argument (rows of OBS_DIM float32, in this machine's byte order, as embedrl writes
 * them), each through policy_step and all of them through policy_step_batch, then the first rows again
 * through policy_step_batch without a status array. Prints one line per observation,
 *
 *   A <index> <code> <hex>...  policy_step's return code and the action's IEEE-754 bits
 *
 * then "BATCH <refused> <rows differing from policy_step>". Exit 0; 2 on a file it cannot read.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The policy's symbols under its name (make passes POLICY_NAME, its upper case and its header). */
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#include COVER_HEADER
#define OBS_DIM CAT(COVER_UP, _OBS_DIM)
#define ACT_DIM CAT(COVER_UP, _ACT_DIM)
#define STEP CAT(COVER_NAME, _step)
#define STEP_BATCH CAT(COVER_NAME, _step_batch)
#define RESET CAT(COVER_NAME, _reset)

#define MAX_ROWS 65536u
#define UNBATCHED_ROWS 3 /* fewer than a block: the batch's short last block, without status */

static float obs[MAX_ROWS][OBS_DIM];
static float act[MAX_ROWS][ACT_DIM];
static float batch_act[MAX_ROWS][ACT_DIM];
static int batch_code[MAX_ROWS];
static int step_code[MAX_ROWS];

static uint32_t bits(float f)
{
    uint32_t u;
    (void)memcpy(&u, &f, sizeof u);
    return u;
}

static long read_rows(const char *path)
{
    FILE *f = fopen(path, "rb");
    if (f == NULL) {
        fprintf(stderr, "cover_policy: cannot open %s\n", path);
        return -1;
    }
    size_t rows = fread(obs, sizeof obs[0], MAX_ROWS, f);
    int extra = fgetc(f);
    (void)fclose(f);
    if (rows == 0u || extra != EOF) {
        fprintf(stderr, "cover_policy: %s holds no rows of %u floats, or more than %u\n", path,
                OBS_DIM, MAX_ROWS);
        return -1;
    }
    return (long)rows;
}

int main(int argc, char **argv)
{
    if (argc != 2) {
        fprintf(stderr, "usage: cover_policy OBSERVATIONS\n");
        return 2;
    }
    long rows = read_rows(argv[1]);
    if (rows < 0) {
        return 2;
    }
    RESET();
    for (long i = 0; i < rows; ++i) {
        step_code[i] = STEP(obs[i], act[i]);
        printf("A %ld %d", i, step_code[i]);
        for (unsigned j = 0; j < ACT_DIM; ++j) {
            printf(" %08lx", (unsigned long)bits(act[i][j]));
        }
        printf("\n");
    }
    RESET();
    int refused = STEP_BATCH((int)rows, &obs[0][0], &batch_act[0][0], batch_code);
    long differing = 0;
    for (long i = 0; i < rows; ++i) {
        differing += (batch_code[i] != step_code[i] || memcmp(batch_act[i], act[i], sizeof act[i]) != 0) ? 1 : 0;
    }
    RESET();
    (void)STEP_BATCH(rows < UNBATCHED_ROWS ? (int)rows : UNBATCHED_ROWS, &obs[0][0], &batch_act[0][0], NULL);
    printf("BATCH %d %ld\n", refused, differing);
    return 0;
}
