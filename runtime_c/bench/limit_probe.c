/* The hardware limit of one inference on this CPU, for `embedrl bench-export`.
 *
 *   limit_probe WEIGHT_BYTES
 *
 * Three probes, each the median of 21 rounds, printed as "name value" lines:
 *   fma_gmacs           multiply-adds per nanosecond of independent fused multiply-adds in the widest
 *                       vectors the compiler targets (-march=native): the arithmetic ceiling;
 *   mul_add_gmacs       the same with each product rounded before its sum (a multiply, then an add) in
 *                       AVX2 vectors, on x86-64 with AVX2 (0 elsewhere): the ceiling of code that must give
 *                       the bits of the baseline build, which has no fused multiply-add (the generated C's
 *                       AVX2 clone);
 *   stream_ns_per_pass  nanoseconds to read WEIGHT_BYTES of floats once, from a buffer read over and over
 *                       (it stays in the nearest cache it fits): the memory ceiling of reading the weights.
 * A dense layer's inference cannot beat either: it multiplies every weight once and reads every weight
 * once. Built with GCC's vector extensions (-std=gnu11), not the portable C99 of the policy. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define ROUNDS 21
#define LANES 16
#define CHAINS 12
#define FMA_ITERATIONS 2000000L

typedef float vec __attribute__((vector_size(LANES * sizeof(float))));

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e9 + (double)t.tv_nsec;
}

static int compare(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static volatile float sink;

/* CHAINS (12) independent accumulators, in registers, hide the FMA latency; each iteration is
 * CHAINS * LANES multiply-adds. */
static double fma_round(void)
{
    vec a, b;
    for (int i = 0; i < LANES; ++i) {
        a[i] = 0.999999f;
        b[i] = 1e-7f;
    }
    vec c0 = a, c1 = a * 2.0f, c2 = a * 3.0f, c3 = a * 4.0f, c4 = a * 5.0f, c5 = a * 6.0f;
    vec c6 = a * 7.0f, c7 = a * 8.0f, c8 = a * 9.0f, c9 = a * 10.0f, c10 = a * 11.0f, c11 = a * 12.0f;
    const double start = now_ns();
    for (long n = 0; n < FMA_ITERATIONS; ++n) {
        c0 = c0 * a + b;
        c1 = c1 * a + b;
        c2 = c2 * a + b;
        c3 = c3 * a + b;
        c4 = c4 * a + b;
        c5 = c5 * a + b;
        c6 = c6 * a + b;
        c7 = c7 * a + b;
        c8 = c8 * a + b;
        c9 = c9 * a + b;
        c10 = c10 * a + b;
        c11 = c11 * a + b;
    }
    const double ns = now_ns() - start;
    const vec total = c0 + c1 + c2 + c3 + c4 + c5 + c6 + c7 + c8 + c9 + c10 + c11;
    float sum = 0.0f;
    for (int i = 0; i < LANES; ++i) {
        sum += total[i];
    }
    sink = sum;
    return (double)FMA_ITERATIONS * CHAINS * LANES / ns;
}

#if defined(__x86_64__)
#define NARROW_LANES 8
typedef float narrow __attribute__((vector_size(NARROW_LANES * sizeof(float))));

/* The empty asm keeps the product in a register between the multiply and the add: no fusing. */
#define MUL_ADD(c) \
    do { \
        narrow t = (c) * a; \
        __asm__("" : "+x"(t)); \
        (c) = t + b; \
    } while (0)

__attribute__((target("avx2"))) static double mul_add_round(void)
{
    narrow a, b;
    for (int i = 0; i < NARROW_LANES; ++i) {
        a[i] = 0.999999f;
        b[i] = 1e-7f;
    }
    narrow c0 = a, c1 = a * 2.0f, c2 = a * 3.0f, c3 = a * 4.0f, c4 = a * 5.0f, c5 = a * 6.0f;
    narrow c6 = a * 7.0f, c7 = a * 8.0f, c8 = a * 9.0f, c9 = a * 10.0f, c10 = a * 11.0f, c11 = a * 12.0f;
    const double start = now_ns();
    for (long n = 0; n < FMA_ITERATIONS; ++n) {
        MUL_ADD(c0);
        MUL_ADD(c1);
        MUL_ADD(c2);
        MUL_ADD(c3);
        MUL_ADD(c4);
        MUL_ADD(c5);
        MUL_ADD(c6);
        MUL_ADD(c7);
        MUL_ADD(c8);
        MUL_ADD(c9);
        MUL_ADD(c10);
        MUL_ADD(c11);
    }
    const double ns = now_ns() - start;
    const narrow total = c0 + c1 + c2 + c3 + c4 + c5 + c6 + c7 + c8 + c9 + c10 + c11;
    float sum = 0.0f;
    for (int i = 0; i < NARROW_LANES; ++i) {
        sum += total[i];
    }
    sink = sum;
    return (double)FMA_ITERATIONS * CHAINS * NARROW_LANES / ns;
}

static double mul_add_probe(void)
{
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") ? mul_add_round() : 0.0;
}
#else
static double mul_add_probe(void)
{
    return 0.0;
}
#endif

static double stream_round(const vec *weights, size_t count, int passes)
{
    vec s0 = {0}, s1 = {0}, s2 = {0}, s3 = {0};
    const double start = now_ns();
    for (int p = 0; p < passes; ++p) {
        size_t i = 0;
        for (; i + 4 <= count; i += 4) {
            s0 += weights[i];
            s1 += weights[i + 1];
            s2 += weights[i + 2];
            s3 += weights[i + 3];
        }
        for (; i < count; ++i) {
            s0 += weights[i];
        }
        __asm__ volatile("" ::: "memory"); /* every pass reads the buffer again */
    }
    const double ns = (now_ns() - start) / passes;
    vec s = s0 + s1 + s2 + s3;
    float total = 0.0f;
    for (int i = 0; i < LANES; ++i) {
        total += s[i];
    }
    sink = total;
    return ns;
}

int main(int argc, char **argv)
{
    const long bytes = argc == 2 ? atol(argv[1]) : 0;
    if (bytes < (long)sizeof(vec) || bytes > (1L << 30)) {
        fprintf(stderr, "usage: limit_probe WEIGHT_BYTES (%zu .. 2^30)\n", sizeof(vec));
        return 2;
    }
    const size_t count = (size_t)bytes / sizeof(vec);
    vec *weights = aligned_alloc(sizeof(vec), count * sizeof(vec));
    if (weights == NULL) {
        return 1;
    }
    for (size_t i = 0; i < count; ++i) {
        for (int k = 0; k < LANES; ++k) {
            weights[i][k] = (float)((i * LANES + (size_t)k) % 7u) * 0.125f;
        }
    }
    const int passes = (int)(200000000L / bytes) + 1;
    double fma[ROUNDS], mul_add[ROUNDS], stream[ROUNDS];
    for (int r = 0; r < ROUNDS; ++r) {
        fma[r] = fma_round();
        mul_add[r] = mul_add_probe();
        stream[r] = stream_round(weights, count, passes);
    }
    qsort(fma, ROUNDS, sizeof(double), compare);
    qsort(mul_add, ROUNDS, sizeof(double), compare);
    qsort(stream, ROUNDS, sizeof(double), compare);
    printf("fma_gmacs %.3f\nmul_add_gmacs %.3f\nstream_ns_per_pass %.2f\nvector_bytes %zu\n", fma[ROUNDS / 2],
           mul_add[ROUNDS / 2], stream[ROUNDS / 2], sizeof(vec));
    free(weights);
    return 0;
}
