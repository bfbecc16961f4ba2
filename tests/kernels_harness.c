/* A standalone program around diffquat's CPU kernels (diffquat/_kernels.c built with
 * DIFFQUAT_KERNELS_ONLY: no Python, no XLA), for tests/test_compilers.py: it runs every kernel in
 * float32 and float64, both storage orders, on deterministic inputs with edge rows, and prints a hash
 * of each output's bytes. Built natively and cross-compiled for aarch64 (run under qemu), the two
 * must print the same lines: the kernels give the same bits where there are no x86 intrinsics. The
 * Jacobian and quaternion_plus kernels call libm's sin and cos, which both glibc builds round alike on these inputs (a
 * change of libm that rounds one of them differently shows here first). */
#define DIFFQUAT_KERNELS_ONLY
#include KERNELS_C /* the path of diffquat/_kernels.c, given by the test */
#include <stdio.h>

#define N 4096

static uint64_t state = 0x9E3779B97F4A7C15ull;
static double uniform(void) { /* xorshift64*: the same numbers on every target */
    state ^= state >> 12, state ^= state << 25, state ^= state >> 27;
    return (double)((state * 0x2545F4914F6CDD1Dull) >> 11) * 0x1.0p-53 * 2.0 - 1.0;
}

static uint64_t fnv(const void *data, size_t size) {
    uint64_t h = 0xcbf29ce484222325ull;
    for (size_t i = 0; i < size; ++i) h = (h ^ ((const unsigned char *)data)[i]) * 0x100000001b3ull;
    return h;
}

/* The Jacobians' series, as diffquat/torch/_cpu.py passes them: given by the test from diffquat._lie. */
static const double series64[] = SERIES_F64, series32[] = SERIES_F32;
static const int64_t terms64[3] = TERMS_F64, terms32[3] = TERMS_F32;
static const double exp64[] = EXP_F64, exp32[] = EXP_F32; /* quaternion_plus: exp_factors' table */

static double w64[N][3];
static float w32[N][3];
/* NaN in one bit pattern: where a kernel's NaN comes from arithmetic (the Jacobians' inf - inf or
 * sin(inf)), its sign is the processor's default NaN (negative on x86-64, positive on aarch64), which
 * is no part of the value. */
static void canonical_nans(void *data, size_t count, int d) {
    for (size_t i = 0; i < count; ++i) {
        if (d && isnan(((double *)data)[i])) ((double *)data)[i] = NAN;
        if (!d && isnan(((float *)data)[i])) ((float *)data)[i] = NAN;
    }
}

static double q64[N][4], m64[N][9], g9_64[N][9], g4_64[N][4], o64[N][9], r64[N][4];
static float q32[N][4], m32[N][9], g9_32[N][9], g4_32[N][4], o32[N][9], r32[N][4];

int main(void) {
    for (int i = 0; i < N; ++i) {
        for (int k = 0; k < 4; ++k) q64[i][k] = uniform(), g4_64[i][k] = uniform();
        for (int k = 0; k < 9; ++k) m64[i][k] = uniform(), g9_64[i][k] = uniform();
    }
    /* edge rows: the zero quaternion, a half-turn, the identity and a half-turn matrix, a NaN */
    for (int k = 0; k < 4; ++k) q64[0][k] = 0, q64[1][k] = k == 1;
    for (int k = 0; k < 9; ++k) m64[0][k] = k % 4 == 0, m64[1][k] = k == 0 ? 1 : k % 4 == 0 ? -1 : 0;
    q64[2][3] = NAN, m64[2][5] = NAN;
    /* rotation vectors up to |w| ~ 7 (the series, the closed forms, past pi); zero, NaN, infinity */
    for (int i = 0; i < N; ++i) {
        for (int k = 0; k < 3; ++k) w64[i][k] = 4 * uniform();
    }
    for (int k = 0; k < 3; ++k) w64[0][k] = 0;
    w64[1][1] = NAN, w64[2][2] = INFINITY;
    for (int i = 0; i < N; ++i) {
        for (int k = 0; k < 3; ++k) w32[i][k] = (float)w64[i][k];
    }
    for (int i = 0; i < N; ++i) {
        for (int k = 0; k < 4; ++k) q32[i][k] = (float)q64[i][k], g4_32[i][k] = (float)g4_64[i][k];
        for (int k = 0; k < 9; ++k) m32[i][k] = (float)m64[i][k], g9_32[i][k] = (float)g9_64[i][k];
    }
    for (int d = 0; d < 2; ++d) {
        for (int first = 0; first < 2; ++first) {
            const void *q = d ? (void *)q64 : (void *)q32, *m = d ? (void *)m64 : (void *)m32;
            void *o = d ? (void *)o64 : (void *)o32, *r = d ? (void *)r64 : (void *)r32;
            size_t size = d ? sizeof(double) : sizeof(float);
            Args a = {.a = q, .sa = {4, 1, 0}, .out = o, .first = first};
            run(KERNELS[Q2M_FORWARD][d], &a, N, 1);
            printf("q2m_forward %d %d %016llx\n", d, first, (unsigned long long)fnv(o, N * 9 * size));
            Args b = {.a = q, .sa = {4, 1, 0}, .b = d ? (void *)g9_64 : (void *)g9_32, .sb = {9, 3, 1},
                      .out = r, .first = first};
            run(KERNELS[Q2M_BACKWARD][d], &b, N, 1);
            printf("q2m_backward %d %d %016llx\n", d, first, (unsigned long long)fnv(r, N * 4 * size));
            Args c = {.a = m, .sa = {9, 3, 1}, .out = r, .first = first};
            run(KERNELS[M2Q_FORWARD][d], &c, N, 1);
            printf("m2q_forward %d %d %016llx\n", d, first, (unsigned long long)fnv(r, N * 4 * size));
            Args e = {.a = m, .sa = {9, 3, 1}, .b = r, .sb = {4, 1, 0}, .c = d ? (void *)g4_64 : (void *)g4_32,
                      .sc = {4, 1, 0}, .out = o, .first = first};
            run(KERNELS[M2Q_BACKWARD][d], &e, N, 1);
            printf("m2q_backward %d %d %016llx\n", d, first, (unsigned long long)fnv(o, N * 9 * size));
        }
    }
    for (int d = 0; d < 2; ++d) {
        for (int kind = 0; kind < 4; ++kind) {
            const void *w = d ? (void *)w64 : (void *)w32;
            void *o = d ? (void *)o64 : (void *)o32, *r = d ? (void *)r64 : (void *)r32;
            size_t size = d ? sizeof(double) : sizeof(float);
            Args a = {.a = w, .sa = {3, 1, 0}, .out = o, .first = kind};
            a.series = d ? series64 : series32;
            for (int k = 0; k < 3; ++k) a.terms[k] = d ? terms64[k] : terms32[k];
            run(KERNELS[JAC_FORWARD][d], &a, N, 1);
            canonical_nans(o, N * 9, d);
            printf("jac_forward %d %d %016llx\n", d, kind, (unsigned long long)fnv(o, N * 9 * size));
            Args b = a;
            b.b = d ? (void *)g9_64 : (void *)g9_32, b.sb[0] = 9, b.sb[1] = 3, b.sb[2] = 1, b.out = r;
            run(KERNELS[JAC_BACKWARD][d], &b, N, 1);
            canonical_nans(r, N * 3, d);
            printf("jac_backward %d %d %016llx\n", d, kind, (unsigned long long)fnv(r, N * 3 * size));
        }
    }
    for (int d = 0; d < 2; ++d) {
        for (int first = 0; first < 2; ++first) {
            for (int right = 0; right < 2; ++right) {
                const void *q = d ? (void *)q64 : (void *)q32, *w = d ? (void *)w64 : (void *)w32;
                void *o = d ? (void *)o64 : (void *)o32, *r = d ? (void *)r64 : (void *)r32;
                size_t size = d ? sizeof(double) : sizeof(float);
                Args a = {.a = q, .sa = {4, 1, 0}, .b = w, .sb = {3, 1, 0}, .out = r, .first = first};
                a.series = d ? exp64 : exp32, a.right = right;
                run(KERNELS[QPLUS_FORWARD][d], &a, N, 1);
                canonical_nans(r, N * 4, d);
                printf("qplus_forward %d %d %d %016llx\n", d, first, right,
                       (unsigned long long)fnv(r, N * 4 * size));
                Args b = a;
                b.c = d ? (void *)g4_64 : (void *)g4_32, b.sc[0] = 4, b.sc[1] = 1, b.out = r, b.out2 = o;
                run(KERNELS[QPLUS_BACKWARD][d], &b, N, 1);
                canonical_nans(r, N * 4, d), canonical_nans(o, N * 3, d);
                printf("qplus_backward %d %d %d %016llx %016llx\n", d, first, right,
                       (unsigned long long)fnv(r, N * 4 * size), (unsigned long long)fnv(o, N * 3 * size));
            }
        }
    }
    return 0;
}
