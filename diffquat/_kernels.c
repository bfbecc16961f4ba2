/* diffquat._kernels: quaternion_to_matrix, matrix_to_quaternion, the SO(3) Jacobians and
 * quaternion_plus on the CPU, forward and backward, each one pass over memory. Two callers:
 * diffquat.torch (Python entry points over raw pointers, below) and diffquat.jax (XLA FFI handlers of
 * matrix_to_quaternion, the Jacobians and quaternion_plus, at the end of this file).
 *
 * The CPU counterpart of diffquat/torch/_triton.py. Eager torch evaluates the core formulas as ~40
 * elementwise operations forward and as many backward, each a full pass over memory and a few
 * microseconds of dispatch; here each direction is one loop over the rotations that reads the inputs
 * once and writes the output once, with no temporaries.
 *
 * The arithmetic is the core's (diffquat/_core.py), operation by operation and in the same order,
 * so that float32 and float64 results agree with the core formula to rounding (the tests compare
 * them at every edge case):
 *   - quaternion_to_matrix: normalise (1 / sqrt of the squared norm, 0 for a squared norm below the
 *     smallest normal number: the zero quaternion gives the identity), then the unit formula;
 *   - its backward: _core.quaternion_to_matrix_cotangent;
 *   - matrix_to_quaternion: the four pivots from the diagonal, the candidate of the largest (ties to
 *     the lower index, as _core._m2q_choice), its normalisation and the canonical sign;
 *   - its backward: _core.matrix_to_quaternion_cotangent, the scale read back from the result.
 *
 * No Python objects are touched inside the loops, so they run without the GIL. It does not depend
 * on torch or jax: torch's side (diffquat/torch/_cpu.py) passes data pointers and strides in
 * elements, so strided inputs (an expanded cotangent, scalar-last storage, a transposed matrix) are
 * read in place instead of copied; XLA passes dense row-major buffers. Outputs are contiguous. Large
 * batches are split over threads.
 */

/* DIFFQUAT_KERNELS_ONLY: the kernels and their thread split alone, without the Python and XLA entry
 * points (no Python headers): what tests/test_kernels.py cross-compiles for aarch64 into a standalone
 * program and runs under qemu, to check that a build without x86 intrinsics gives the same bits. */
#if !defined(DIFFQUAT_KERNELS_ONLY)
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#endif

#include <float.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stddef.h>
#include <unistd.h>
#include <stdint.h>

/* Everything a kernel needs, as the Python side passed it. Strides are in elements. */
typedef struct {
    const void *a;     /* q (quaternion_to_matrix*) or the matrix (matrix_to_quaternion*) */
    const void *b;     /* dL/dR (q2m backward) or the result q (m2q backward) */
    const void *c;     /* dL/dq (m2q backward) */
    void *out;         /* contiguous output */
    void *out2;        /* a second contiguous output (quaternion_plus backward: dL/dd) */
    int64_t sa[3];     /* strides of a: row, then (component) or (matrix row, matrix column) */
    int64_t sb[3];
    int64_t sc[3];
    int first;         /* storage order of every quaternion read or written: 1 = (w, x, y, z); */
                       /* for the Jacobians, which one (0 J_l, 1 J_r, 2 J_l^-1, 3 J_r^-1) */
    const double *series; /* the Jacobians' series: the threshold in u, then the coefficients */
    int64_t terms[3];  /* how many coefficients of each of the three series follow */
    int right;         /* quaternion_plus: 1 for q exp(d), 0 for exp(d) q */
} Args;

typedef void (*Kernel)(const Args *, int64_t, int64_t);

/* Each kernel works by blocks of BLOCK rows: the inputs are gathered into one array per component
 * (in storage order), the arithmetic runs over those arrays (branch-free: the pivot choice and the
 * sign rule are selects and bitwise masks, so the compiler vectorises it), and the results are
 * scattered into the contiguous output. Strided inputs are read in place by a generic gather;
 * contiguous rows, the common case, by fixed offsets, and for float32 on x86-64 four rows at a time
 * through SSE transposes, which compilers do not find by themselves for rows of 9. On x86-64 each
 * kernel is also compiled for AVX2, and the loader picks the build that the processor runs
 * (target_clones); FMA stays off, so every build rounds as the core does. */
#define BLOCK 128
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(DIFFQUAT_PORTABLE)
#define CLONES __attribute__((target_clones("default", "avx2")))
#else
#define CLONES
#endif

/* Index in storage order of component k (0: w, 1: x, 2: y, 3: z). */
static inline int component(int first, int k) { return first ? k : (k + 3) % 4; }

/* Moves of one block of `cnt` rows, v[e][j] = entry e of row j: strided gathers (strides in
 * elements), and gathers and scatters of contiguous rows of 4 or 9. */
#define DEFINE_STRIDED(T, SUFFIX)                                                                   \
    static inline void gather4_strided_##SUFFIX(T v[4][BLOCK], const T *src, int64_t rs,            \
                                                int64_t cs, int cnt) {                              \
        for (int j = 0; j < cnt; ++j) {                                                             \
            for (int e = 0; e < 4; ++e) v[e][j] = src[j * rs + e * cs];                             \
        }                                                                                           \
    }                                                                                               \
    static inline void gather9_strided_##SUFFIX(T v[9][BLOCK], const T *src, int64_t rs,            \
                                                int64_t is, int64_t js, int cnt) {                  \
        for (int j = 0; j < cnt; ++j) {                                                             \
            for (int e = 0; e < 9; ++e) v[e][j] = src[j * rs + (e / 3) * is + (e % 3) * js];        \
        }                                                                                           \
    }

/* Contiguous rows of W entries, one row at a time from `from` on (the whole block, or what is left
 * after the vectorised part). */
#define DEFINE_ROWS(T, SUFFIX, W)                                                                   \
    static inline void gather##W##_tail_##SUFFIX(T v[W][BLOCK], const T *src, int from, int cnt) {  \
        for (int j = from; j < cnt; ++j) {                                                          \
            for (int e = 0; e < W; ++e) v[e][j] = src[W * j + e];                                   \
        }                                                                                           \
    }                                                                                               \
    static inline void scatter##W##_tail_##SUFFIX(T *dst, T v[W][BLOCK], int from, int cnt) {       \
        for (int j = from; j < cnt; ++j) {                                                          \
            for (int e = 0; e < W; ++e) dst[W * j + e] = v[e][j];                                   \
        }                                                                                           \
    }

DEFINE_STRIDED(float, f32)
DEFINE_STRIDED(double, f64)
DEFINE_ROWS(float, f32, 4)
DEFINE_ROWS(float, f32, 9)
DEFINE_ROWS(double, f64, 4)
DEFINE_ROWS(double, f64, 9)

/* DIFFQUAT_PORTABLE (a build the tests make, see tests/test_kernels.py) keeps to the plain loops. */
#if defined(__SSE2__) && !defined(DIFFQUAT_PORTABLE)
#define FAST_MOVES 1
#include <immintrin.h>
/* The fast moves of contiguous rows ("_fast_"): they move as many rows as they can and return how
 * many; the one-row loops above ("_tail_") do the rest. float32 on x86-64: four rows at a time, a
 * 4 x 4 transpose per four entries (a row of 9 is two vectors and one scalar). */
static inline void store_columns(float v[][BLOCK], int e, int j, __m128 a0, __m128 a1, __m128 a2,
                                 __m128 a3) {
    _MM_TRANSPOSE4_PS(a0, a1, a2, a3);
    _mm_storeu_ps(&v[e][j], a0), _mm_storeu_ps(&v[e + 1][j], a1);
    _mm_storeu_ps(&v[e + 2][j], a2), _mm_storeu_ps(&v[e + 3][j], a3);
}
static inline int gather4_fast_f32(float v[4][BLOCK], const float *src, int cnt) {
    int j = 0;
    for (; j + 4 <= cnt; j += 4) {
        const float *s = src + 4 * j;
        store_columns(v, 0, j, _mm_loadu_ps(s), _mm_loadu_ps(s + 4), _mm_loadu_ps(s + 8),
                      _mm_loadu_ps(s + 12));
    }
    return j;
}
static inline int gather9_fast_f32(float v[9][BLOCK], const float *src, int cnt) {
    int j = 0;
    for (; j + 4 <= cnt; j += 4) {
        const float *s = src + 9 * j;
        store_columns(v, 0, j, _mm_loadu_ps(s), _mm_loadu_ps(s + 9), _mm_loadu_ps(s + 18),
                      _mm_loadu_ps(s + 27));
        store_columns(v, 4, j, _mm_loadu_ps(s + 4), _mm_loadu_ps(s + 13), _mm_loadu_ps(s + 22),
                      _mm_loadu_ps(s + 31));
        v[8][j] = s[8], v[8][j + 1] = s[17], v[8][j + 2] = s[26], v[8][j + 3] = s[35];
    }
    return j;
}
static inline int scatter4_fast_f32(float *dst, float v[4][BLOCK], int cnt) {
    int j = 0;
    for (; j + 4 <= cnt; j += 4) {
        __m128 a0 = _mm_loadu_ps(&v[0][j]), a1 = _mm_loadu_ps(&v[1][j]);
        __m128 a2 = _mm_loadu_ps(&v[2][j]), a3 = _mm_loadu_ps(&v[3][j]);
        _MM_TRANSPOSE4_PS(a0, a1, a2, a3);
        float *o = dst + 4 * j;
        _mm_storeu_ps(o, a0), _mm_storeu_ps(o + 4, a1), _mm_storeu_ps(o + 8, a2);
        _mm_storeu_ps(o + 12, a3);
    }
    return j;
}
static inline int scatter9_fast_f32(float *dst, float v[9][BLOCK], int cnt) {
    int j = 0;
    for (; j + 4 <= cnt; j += 4) {
        __m128 a0 = _mm_loadu_ps(&v[0][j]), a1 = _mm_loadu_ps(&v[1][j]);
        __m128 a2 = _mm_loadu_ps(&v[2][j]), a3 = _mm_loadu_ps(&v[3][j]);
        __m128 b0 = _mm_loadu_ps(&v[4][j]), b1 = _mm_loadu_ps(&v[5][j]);
        __m128 b2 = _mm_loadu_ps(&v[6][j]), b3 = _mm_loadu_ps(&v[7][j]);
        _MM_TRANSPOSE4_PS(a0, a1, a2, a3);
        _MM_TRANSPOSE4_PS(b0, b1, b2, b3);
        float *o = dst + 9 * j;
        _mm_storeu_ps(o, a0), _mm_storeu_ps(o + 4, b0), o[8] = v[8][j];
        _mm_storeu_ps(o + 9, a1), _mm_storeu_ps(o + 13, b1), o[17] = v[8][j + 1];
        _mm_storeu_ps(o + 18, a2), _mm_storeu_ps(o + 22, b2), o[26] = v[8][j + 2];
        _mm_storeu_ps(o + 27, a3), _mm_storeu_ps(o + 31, b3), o[35] = v[8][j + 3];
    }
    return j;
}
#endif
/* Without such moves (float64; float32 off x86-64) every row goes through the one-row loops, whose
 * fixed offsets the compiler vectorises where it can: the fast moves move no row. */
#define DEFINE_NO_FAST_MOVES(T, SUFFIX)                                                             \
    static inline int gather4_fast_##SUFFIX(T v[4][BLOCK], const T *src, int cnt) {                 \
        (void)v, (void)src, (void)cnt;                                                              \
        return 0;                                                                                   \
    }                                                                                               \
    static inline int gather9_fast_##SUFFIX(T v[9][BLOCK], const T *src, int cnt) {                 \
        (void)v, (void)src, (void)cnt;                                                              \
        return 0;                                                                                   \
    }                                                                                               \
    static inline int scatter4_fast_##SUFFIX(T *dst, T v[4][BLOCK], int cnt) {                      \
        (void)dst, (void)v, (void)cnt;                                                              \
        return 0;                                                                                   \
    }                                                                                               \
    static inline int scatter9_fast_##SUFFIX(T *dst, T v[9][BLOCK], int cnt) {                      \
        (void)dst, (void)v, (void)cnt;                                                              \
        return 0;                                                                                   \
    }
#if !defined(FAST_MOVES)
DEFINE_NO_FAST_MOVES(float, f32)
#endif
DEFINE_NO_FAST_MOVES(double, f64)

/* A block of quaternions (strides s: row, component) or of matrices (row, matrix row, matrix
 * column) from row `base` on, gathered in storage order; a block of contiguous output rows. */
#define DEFINE_MOVES(T, SUFFIX)                                                                     \
    static inline void gather4_##SUFFIX(T v[4][BLOCK], const T *src, const int64_t *s,              \
                                        int64_t base, int cnt) {                                    \
        if (s[0] == 4 && s[1] == 1) {                                                               \
            const T *rows = src + 4 * base;                                                         \
            gather4_tail_##SUFFIX(v, rows, gather4_fast_##SUFFIX(v, rows, cnt), cnt);               \
        } else {                                                                                    \
            gather4_strided_##SUFFIX(v, src + base * s[0], s[0], s[1], cnt);                        \
        }                                                                                           \
    }                                                                                               \
    static inline void gather9_##SUFFIX(T v[9][BLOCK], const T *src, const int64_t *s,              \
                                        int64_t base, int cnt) {                                    \
        if (s[0] == 9 && s[1] == 3 && s[2] == 1) {                                                  \
            const T *rows = src + 9 * base;                                                         \
            gather9_tail_##SUFFIX(v, rows, gather9_fast_##SUFFIX(v, rows, cnt), cnt);               \
        } else {                                                                                    \
            gather9_strided_##SUFFIX(v, src + base * s[0], s[0], s[1], s[2], cnt);                  \
        }                                                                                           \
    }                                                                                               \
    static inline void scatter4_##SUFFIX(T *dst, T v[4][BLOCK], int cnt) {                          \
        scatter4_tail_##SUFFIX(dst, v, scatter4_fast_##SUFFIX(dst, v, cnt), cnt);                   \
    }                                                                                               \
    static inline void scatter9_##SUFFIX(T *dst, T v[9][BLOCK], int cnt) {                          \
        scatter9_tail_##SUFFIX(dst, v, scatter9_fast_##SUFFIX(dst, v, cnt), cnt);                   \
    }

DEFINE_MOVES(float, f32)
DEFINE_MOVES(double, f64)

/* Whether every value is finite: a value times 0 is 0 for a finite one and NaN for an infinity or a
 * NaN, so the sum of such products is 0 exactly when all are finite (branch-free, and no sum of the
 * values themselves, which could overflow). */
#define FINITE4(a, b, c, d) ((a) * 0 + (b) * 0 + (c) * 0 + (d) * 0 == 0)
#define FINITE9(m, j)                                                                               \
    ((m)[0][j] * 0 + (m)[1][j] * 0 + (m)[2][j] * 0 + (m)[3][j] * 0 + (m)[4][j] * 0 + (m)[5][j] * 0 + \
         (m)[6][j] * 0 + (m)[7][j] * 0 + (m)[8][j] * 0 ==                                           \
     0)

/* _core._unit_components, declaring big (the largest component, 1 for the zero quaternion), inv
 * (1 / |q / big|, 0 for the zero quaternion) and the unit components uw .. uz: the quaternion is
 * divided by its largest component before it is normalised (the squared norm then lies in [1, 4]), so
 * every finite norm whose square is normal works; the zero quaternion (squared norm below the smallest
 * normal number) takes 1/|q| = 0, the identity. T, TINY and SQRT are the kernel's type and its
 * smallest normal number and square root. */
#define UNIT(T, TINY, SQRT, W, X, Y, Z)                                                                          \
    T n2 = (W) * (W) + (X) * (X) + (Y) * (Y) + (Z) * (Z);                                           \
    const int nonzero = n2 >= TINY;                                                                \
    T aw = (W) < 0 ? -(W) : (W), ax = (X) < 0 ? -(X) : (X);                                         \
    T ay = (Y) < 0 ? -(Y) : (Y), az = (Z) < 0 ? -(Z) : (Z);                                         \
    T a01 = aw >= ax ? aw : ax, a23 = ay >= az ? ay : az;                                           \
    T big = nonzero ? (a01 >= a23 ? a01 : a23) : (T)1;                                              \
    T pw = (W) / big, px = (X) / big, py = (Y) / big, pz = (Z) / big;                               \
    T inv = nonzero ? (T)1 / SQRT(pw * pw + px * px + py * py + pz * pz) : (T)0;                    \
    T uw = pw * inv, ux = px * inv, uy = py * inv, uz = pz * inv

#define DEFINE_KERNELS(T, SUFFIX, TINY, SQRT)                                                        \
    CLONES static void q2m_forward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {        \
        T v[4][BLOCK], r[9][BLOCK];                                                                 \
        const int f = args->first;                                                                  \
        const T *w = v[component(f, 0)], *x = v[component(f, 1)];                                   \
        const T *y = v[component(f, 2)], *z = v[component(f, 3)];                                   \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather4_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                UNIT(T, TINY, SQRT, w[j], x[j], y[j], z[j]);                                        \
                T x2 = (T)2 * ux, y2 = (T)2 * uy, z2 = (T)2 * uz;                                   \
                T xx = x2 * ux, yy = y2 * uy, zz = z2 * uz;                                         \
                T xy = x2 * uy, xz = x2 * uz, yz = y2 * uz;                                         \
                T wx = x2 * uw, wy = y2 * uw, wz = z2 * uw;                                         \
                r[0][j] = (T)1 - (yy + zz), r[1][j] = xy - wz, r[2][j] = xz + wy;                   \
                r[3][j] = xy + wz, r[4][j] = (T)1 - (xx + zz), r[5][j] = yz - wx;                   \
                r[6][j] = xz - wy, r[7][j] = yz + wx, r[8][j] = (T)1 - (xx + yy);                   \
                /* a non-finite component makes the whole row NaN (diffquat._backend.nonfinite_rows); */ \
                /* selects, which the compiler turns into blends */                                 \
                const int ok = FINITE4(w[j], x[j], y[j], z[j]);                                     \
                for (int e = 0; e < 9; ++e) r[e][j] = ok ? r[e][j] : (T)NAN;                        \
            }                                                                                       \
            scatter9_##SUFFIX((T *)args->out + 9 * base, r, cnt);                                   \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void q2m_backward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {       \
        T v[4][BLOCK], g[9][BLOCK], r[4][BLOCK];                                                    \
        const int f = args->first;                                                                  \
        const T *w = v[component(f, 0)], *x = v[component(f, 1)];                                   \
        const T *y = v[component(f, 2)], *z = v[component(f, 3)];                                   \
        T *rw = r[component(f, 0)], *rx = r[component(f, 1)];                                      \
        T *ry = r[component(f, 2)], *rz = r[component(f, 3)];                                       \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather4_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            gather9_##SUFFIX(g, (const T *)args->b, args->sb, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                UNIT(T, TINY, SQRT, w[j], x[j], y[j], z[j]);                                        \
                T g00 = g[0][j], g01 = g[1][j], g02 = g[2][j];                                      \
                T g10 = g[3][j], g11 = g[4][j], g12 = g[5][j];                                      \
                T g20 = g[6][j], g21 = g[7][j], g22 = g[8][j];                                      \
                T wx = g21 - g12, wy = g02 - g20, wz = g10 - g01;                                   \
                T xy = g01 + g10, xz = g02 + g20, yz = g12 + g21;                                   \
                T trace = g00 + g11 + g22;                                                          \
                T gw = wx * ux + wy * uy + wz * uz;                                                 \
                T gx = wx * uw + xy * uy + xz * uz + (T)2 * (g00 - trace) * ux;                     \
                T gy = wy * uw + xy * ux + yz * uz + (T)2 * (g11 - trace) * uy;                     \
                T gz = wz * uw + xz * ux + yz * uy + (T)2 * (g22 - trace) * uz;                     \
                T radial = uw * gw + ux * gx + uy * gy + uz * gz;                                   \
                T s = (T)2 * (inv / big);                                                           \
                rw[j] = s * (gw - radial * uw), rx[j] = s * (gx - radial * ux);                     \
                ry[j] = s * (gy - radial * uy), rz[j] = s * (gz - radial * uz);                     \
            }                                                                                       \
            scatter4_##SUFFIX((T *)args->out + 4 * base, r, cnt);                                   \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void m2q_forward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {        \
        T m[9][BLOCK], r[4][BLOCK];                                                                 \
        const int f = args->first;                                                                  \
        T *rw = r[component(f, 0)], *rx = r[component(f, 1)];                                      \
        T *ry = r[component(f, 2)], *rz = r[component(f, 3)];                                       \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather9_##SUFFIX(m, (const T *)args->a, args->sa, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                /* a quarter of the matrix (exact): sums of four quarters cannot overflow */       \
                const T h = (T)0.25;                                                                \
                T m00 = h * m[0][j], m01 = h * m[1][j], m02 = h * m[2][j];                          \
                T m10 = h * m[3][j], m11 = h * m[4][j], m12 = h * m[5][j];                          \
                T m20 = h * m[6][j], m21 = h * m[7][j], m22 = h * m[8][j];                          \
                T t0 = h + m00 + m11 + m22, t1 = h + m00 - m11 - m22;                               \
                T t2 = h - m00 + m11 - m22, t3 = h - m00 - m11 + m22;                               \
                T wx = m21 - m12, wy = m02 - m20, wz = m10 - m01;                                   \
                T xy = m01 + m10, xz = m02 + m20, yz = m12 + m21;                                   \
                /* _core._m2q_choice: the larger pair, then the larger of it, ties to the lower */ \
                T high01 = t0 >= t1 ? t0 : t1, high23 = t2 >= t3 ? t2 : t3;                         \
                int use01 = high01 >= high23, use0 = t0 >= t1, use2 = t2 >= t3;                     \
                T w = use01 ? (use0 ? t0 : wx) : (use2 ? wy : wz);                                  \
                T x = use01 ? (use0 ? wx : t1) : (use2 ? xy : xz);                                  \
                T y = use01 ? (use0 ? wy : xy) : (use2 ? t2 : yz);                                  \
                T z = use01 ? (use0 ? wz : xz) : (use2 ? yz : t3);                                  \
                /* _core._m2q_unit: divided by the largest component (>= the chosen pivot >= 1/4), */ \
                /* so that the squares cannot overflow; the scaled norm lies in [1, 2] */          \
                T aw = w < 0 ? -w : w, ax = x < 0 ? -x : x, ay = y < 0 ? -y : y, az = z < 0 ? -z : z; \
                T a01 = aw >= ax ? aw : ax, a23 = ay >= az ? ay : az;                               \
                T big = a01 >= a23 ? a01 : a23;                                                     \
                w = w / big, x = x / big, y = y / big, z = z / big;                                 \
                T inv = (T)1 / SQRT(w * w + x * x + y * y + z * z);                                 \
                /* _core._negative_canonical, with bitwise operators: no branches */               \
                int negative = (w < 0) |                                                            \
                               ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0)))))); \
                inv = negative ? -inv : inv;                                                        \
                /* a non-finite entry makes the whole row NaN (diffquat._backend.nonfinite_rows) */ \
                inv = FINITE9(m, j) ? inv : (T)NAN;                                                 \
                rw[j] = w * inv, rx[j] = x * inv, ry[j] = y * inv, rz[j] = z * inv;                 \
            }                                                                                       \
            scatter4_##SUFFIX((T *)args->out + 4 * base, r, cnt);                                   \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void m2q_backward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {       \
        T m[9][BLOCK], v[4][BLOCK], h[4][BLOCK], r[9][BLOCK];                                       \
        const int f = args->first;                                                                  \
        const T *qw = v[component(f, 0)], *qx = v[component(f, 1)];                                 \
        const T *qy = v[component(f, 2)], *qz = v[component(f, 3)];                                 \
        const T *hw = h[component(f, 0)], *hx = h[component(f, 1)];                                 \
        const T *hy = h[component(f, 2)], *hz = h[component(f, 3)];                                 \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather9_##SUFFIX(m, (const T *)args->a, args->sa, base, cnt);                           \
            gather4_##SUFFIX(v, (const T *)args->b, args->sb, base, cnt);                           \
            gather4_##SUFFIX(h, (const T *)args->c, args->sc, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                /* the choice needs only the diagonal */                                            \
                T m00 = m[0][j], m11 = m[4][j], m22 = m[8][j];                                      \
                T t0 = (T)1 + m00 + m11 + m22, t1 = (T)1 + m00 - m11 - m22;                         \
                T t2 = (T)1 - m00 + m11 - m22, t3 = (T)1 - m00 - m11 + m22;                         \
                T high01 = t0 >= t1 ? t0 : t1, high23 = t2 >= t3 ? t2 : t3;                         \
                int use01 = high01 >= high23, use0 = t0 >= t1, use2 = t2 >= t3;                     \
                T largest = use01 ? high01 : high23;                                                \
                T w = qw[j], x = qx[j], y = qy[j], z = qz[j];                                       \
                /* the scale +-1/|c| read back from q: component k of candidate k is the pivot */  \
                /* t_k, and the largest pivot is at least 1 */                                      \
                T inv = (use01 ? (use0 ? w : x) : (use2 ? y : z)) / largest;                        \
                T dot = w * hw[j] + x * hx[j] + y * hy[j] + z * hz[j];                              \
                T gw = inv * (hw[j] - w * dot), gx = inv * (hx[j] - x * dot);                       \
                T gy = inv * (hy[j] - y * dot), gz = inv * (hz[j] - z * dot);                       \
                /* row and column k of the symmetric K (row k = candidate k) receive the        */ \
                /* candidate's cotangent: nested selects on the two-level choice, as in the     */ \
                /* forward, which the compiler vectorises (integer masks it did not)            */ \
                T tw = use01 ? (use0 ? gw : (T)0) : (T)0, tx = use01 ? (use0 ? (T)0 : gx) : (T)0;   \
                T ty = use01 ? (T)0 : (use2 ? gy : (T)0), tz = use01 ? (T)0 : (use2 ? (T)0 : gz);   \
                T cwx = use01 ? (use0 ? gx : gw) : (T)0;                                            \
                T cwy = use01 ? (use0 ? gy : (T)0) : (use2 ? gw : (T)0);                            \
                T cwz = use01 ? (use0 ? gz : (T)0) : (use2 ? (T)0 : gw);                            \
                T cxy = use01 ? (use0 ? (T)0 : gy) : (use2 ? gx : (T)0);                            \
                T cxz = use01 ? (use0 ? (T)0 : gz) : (use2 ? (T)0 : gx);                            \
                T cyz = use01 ? (T)0 : (use2 ? gz : gy);                                            \
                r[0][j] = tw + tx - ty - tz, r[1][j] = cxy - cwz, r[2][j] = cwy + cxz;              \
                r[3][j] = cwz + cxy, r[4][j] = tw - tx + ty - tz, r[5][j] = cyz - cwx;              \
                r[6][j] = cxz - cwy, r[7][j] = cwx + cyz, r[8][j] = tw - tx - ty + tz;              \
            }                                                                                       \
            scatter9_##SUFFIX((T *)args->out + 9 * base, r, cnt);                                   \
        }                                                                                           \
    }

DEFINE_KERNELS(float, f32, FLT_MIN, sqrtf)
DEFINE_KERNELS(double, f64, DBL_MIN, sqrt)

/* ---------------------------------------------------------------------------------------------
 * The Jacobians of SO(3) (diffquat/_lie.py): J = p I + q hat(w) + r w w^T, forward (w -> J) and
 * backward (w, dL/dJ -> dL/dw), one kernel each for the four of them (kind: 0 J_l, 1 J_r, 2 J_l^-1,
 * 3 J_r^-1). The forward is _lie._jacobian_coefficients / _inverse_coefficients and _lie._assemble,
 * operation by operation: Taylor series in u = |w|^2 below the core's threshold, closed forms in
 * half angles above (sin and cos from libm), both evaluated and one selected. The series' threshold
 * and coefficients, truncated for the dtype as the core truncates them, come from the core's table
 * (Args.series, filled by diffquat/torch/_cpu.py): one table, not a copy of it.
 *
 * The backward is the derivative of that forward, written out: with p', q', r' the derivatives in u,
 *   dL/dw = 2 (p' tr G + q' <G, hat(w)> + r' w^T G w) w + q vee(G - G^T) + r (G + G^T) w,
 * where vee(G - G^T) = (G21 - G12, G02 - G20, G10 - G01) is the derivative of <G, hat(w)>. Below the
 * threshold p', q', r' are the derivatives of the truncated series (what autodiff of the core's
 * Horner evaluation computes); above, identities of the closed forms that need no further sines:
 *   J:    p' = (r - q) / 2, q' = (p - 2 q) / (2 u), r' = (q - 3 r) / (2 u)
 *   J^-1: p' = (p r - 1/4) / 2, r' = -(p' + r) / u            (q is the constant -+1/2)
 * They cancel where the closed forms do (at small t, where the series is used instead): from the
 * threshold t = 1 on, r' loses at most ~6 bits of itself, a part in 1e4 of the gradient's scale. */
#define MAX_TERMS 16

#define DEFINE_JACOBIANS(T, SUFFIX, SQRT, SIN, COS)                                                  \
    typedef struct {                                                                                \
        T below;                       /* the threshold in u */                                     \
        T c[3][MAX_TERMS], d[3][MAX_TERMS]; /* (1 - cos t)/t^2, (t - sin t)/t^3, J^-1's r; d/du */  \
        int n[3];                                                                                   \
    } Series_##SUFFIX;                                                                              \
                                                                                                    \
    static void series_##SUFFIX(Series_##SUFFIX *s, const Args *args) {                             \
        const double *table = args->series;                                                         \
        s->below = (T)table[0];                                                                     \
        int64_t at = 1;                                                                             \
        for (int k = 0; k < 3; ++k) {                                                               \
            s->n[k] = (int)args->terms[k];                                                          \
            for (int i = 0; i < s->n[k]; ++i) s->c[k][i] = (T)table[at + i];                        \
            for (int i = 0; i + 1 < s->n[k]; ++i) s->d[k][i] = (T)((double)(i + 1) * table[at + i + 1]); \
            at += s->n[k];                                                                          \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    /* _lie._series: Horner's rule, as the core writes it (n >= 2 terms) */                         \
    static inline T horner_##SUFFIX(const T *c, int n, T u) {                                       \
        T out = c[n - 1] * u + c[n - 2];                                                            \
        for (int i = n - 3; i >= 0; --i) out = out * u + c[i];                                      \
        return out;                                                                                 \
    }                                                                                               \
                                                                                                    \
    /* (p, q, r) and their derivatives in u (d[0..3)) at u = |w|^2; q is J_l's (kinds 0 and 1) or */ \
    /* 0 (the inverses, whose q is a constant the caller adds) */                                   \
    static inline void coefficients_##SUFFIX(const Series_##SUFFIX *s, int inverse, T u, T c[3],    \
                                             T d[3], int derivatives) {                             \
        const int small = u < s->below;                                                             \
        const T us = small ? u : (T)0, uc = small ? s->below : u, t = SQRT(uc);                     \
        if (!inverse) {                                                                             \
            const T rs = horner_##SUFFIX(s->c[1], s->n[1], us);                                     \
            const T sin_t = SIN(t), sin_half = SIN((T)0.5 * t);                                     \
            const T pc = sin_t / t, qc = (T)2 * (sin_half * sin_half) / uc;                         \
            const T rc = (t - sin_t) / (t * uc);                                                    \
            c[0] = small ? (T)1 - us * rs : pc;                                                     \
            c[1] = small ? horner_##SUFFIX(s->c[0], s->n[0], us) : qc;                              \
            c[2] = small ? rs : rc;                                                                 \
            if (derivatives) {                                                                      \
                const T drs = horner_##SUFFIX(s->d[1], s->n[1] - 1, us);                            \
                d[0] = small ? -(rs + us * drs) : (rc - qc) * (T)0.5;                               \
                d[1] = small ? horner_##SUFFIX(s->d[0], s->n[0] - 1, us) : (pc - (T)2 * qc) / ((T)2 * uc); \
                d[2] = small ? drs : (qc - (T)3 * rc) / ((T)2 * uc);                                \
            }                                                                                       \
        } else {                                                                                    \
            const T rs = horner_##SUFFIX(s->c[2], s->n[2], us);                                     \
            const T half = (T)0.5 * t;                                                              \
            const T pc = half * COS(half) / SIN(half), rc = ((T)1 - pc) / uc;                       \
            c[0] = small ? (T)1 - us * rs : pc;                                                     \
            c[1] = (T)0;                                                                            \
            c[2] = small ? rs : rc;                                                                 \
            if (derivatives) {                                                                      \
                const T drs = horner_##SUFFIX(s->d[2], s->n[2] - 1, us);                            \
                const T dpc = (pc * rc - (T)0.25) * (T)0.5;                                         \
                d[0] = small ? -(rs + us * drs) : dpc;                                              \
                d[1] = (T)0;                                                                        \
                d[2] = small ? drs : -(dpc + rc) / uc;                                              \
            }                                                                                       \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    /* the factor of hat(w) and its derivative in u, by kind: q, -q, -1/2, 1/2 */                   \
    static inline T skew_##SUFFIX(int kind, T q) {                                                  \
        return kind == 0 ? q : kind == 1 ? -q : kind == 2 ? (T)-0.5 : (T)0.5;                       \
    }                                                                                               \
                                                                                                    \
    static inline void gather3_##SUFFIX(T v[3][BLOCK], const T *src, const int64_t *s, int64_t base, \
                                        int cnt) {                                                  \
        const T *rows = src + base * s[0];                                                          \
        for (int j = 0; j < cnt; ++j) {                                                             \
            for (int e = 0; e < 3; ++e) v[e][j] = rows[j * s[0] + e * s[1]];                        \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void jac_forward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {        \
        T v[3][BLOCK], m[9][BLOCK];                                                                 \
        Series_##SUFFIX s;                                                                          \
        series_##SUFFIX(&s, args);                                                                  \
        const int kind = args->first, inverse = kind >= 2;                                          \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather3_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                const T x = v[0][j], y = v[1][j], z = v[2][j];                                      \
                T c[3], d[3];                                                                       \
                coefficients_##SUFFIX(&s, inverse, x * x + y * y + z * z, c, d, 0);                 \
                const T p = c[0], q = skew_##SUFFIX(kind, c[1]), r = c[2];                          \
                /* _lie._assemble */                                                                \
                const T rx = r * x, ry = r * y, rxy = rx * y, rxz = rx * z, ryz = ry * z;           \
                const T qx = q * x, qy = q * y, qz = q * z;                                         \
                m[0][j] = p + rx * x, m[1][j] = rxy - qz, m[2][j] = rxz + qy;                       \
                m[3][j] = rxy + qz, m[4][j] = p + ry * y, m[5][j] = ryz - qx;                       \
                m[6][j] = rxz - qy, m[7][j] = ryz + qx, m[8][j] = p + (r * z) * z;                  \
            }                                                                                       \
            scatter9_##SUFFIX((T *)args->out + 9 * base, m, cnt);                                   \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void jac_backward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {       \
        T v[3][BLOCK], g[9][BLOCK];                                                                 \
        Series_##SUFFIX s;                                                                          \
        series_##SUFFIX(&s, args);                                                                  \
        const int kind = args->first, inverse = kind >= 2;                                          \
        const T flip = kind == 1 ? (T)-1 : (T)1; /* J_r = J_l(-w): its q' is -q' */                 \
        T *out = (T *)args->out;                                                                    \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather3_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            gather9_##SUFFIX(g, (const T *)args->b, args->sb, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                const T x = v[0][j], y = v[1][j], z = v[2][j];                                      \
                T c[3], d[3];                                                                       \
                coefficients_##SUFFIX(&s, inverse, x * x + y * y + z * z, c, d, 1);                 \
                const T q = skew_##SUFFIX(kind, c[1]), r = c[2];                                    \
                const T g0 = g[0][j], g1 = g[1][j], g2 = g[2][j], g3 = g[3][j], g4 = g[4][j];       \
                const T g5 = g[5][j], g6 = g[6][j], g7 = g[7][j], g8 = g[8][j];                     \
                const T vx = g7 - g5, vy = g2 - g6, vz = g3 - g1;                                   \
                const T gx = g0 * x + g1 * y + g2 * z, gy = g3 * x + g4 * y + g5 * z;               \
                const T gz = g6 * x + g7 * y + g8 * z;                                              \
                const T hx = g0 * x + g3 * y + g6 * z, hy = g1 * x + g4 * y + g7 * z;               \
                const T hz = g2 * x + g5 * y + g8 * z;                                              \
                T k = d[0] * (g0 + g4 + g8) + d[2] * (x * gx + y * gy + z * gz);                    \
                if (!inverse) k = k + flip * d[1] * (x * vx + y * vy + z * vz);                     \
                k = (T)2 * k;                                                                       \
                T *o = out + 3 * (base + j);                                                        \
                o[0] = k * x + q * vx + r * (gx + hx);                                              \
                o[1] = k * y + q * vy + r * (gy + hy);                                              \
                o[2] = k * z + q * vz + r * (gz + hz);                                              \
            }                                                                                       \
        }                                                                                           \
    }

DEFINE_JACOBIANS(float, f32, sqrtf, sinf, cosf)
DEFINE_JACOBIANS(double, f64, sqrt, sin, cos)

/* ---------------------------------------------------------------------------------------------
 * quaternion_plus (diffquat/_lie.py): q exp(d) (right) or exp(d) q (left), as a unit quaternion,
 * forward (q, d -> the product) and backward (q, d, dL/dout -> dL/dq, dL/dd). The forward is
 * _lie._unit (q divided by its largest component, then normalised; the zero quaternion is the
 * identity), _algebra.exp_factors (cos(t/2) and sin(t/2)/t of t^2 = |d|^2: a Taylor series below the
 * core's threshold, whose coefficients and threshold come from the core's table, Args.series) and
 * _lie._product, operation by operation. Non-finite rows come out NaN by the same arithmetic (a NaN or
 * an infinity reaches every component through the norm of q or the angle of d).
 *
 * The backward is the derivative written out. For out = a b (Hamilton product), dL/da = g b* and
 * dL/db = a* g (the multiplication matrices of b and b* are transposes of each other, for any b);
 * through the normalisation u = s / |s| with s = q / big (big, the largest component, is a constant:
 * it cancels), dL/dq = (dL/du - u <u, dL/du>) / |s| / big, 0 for the zero quaternion; through the step
 * (w, k d), dL/dd = k dL/dv + 2 d (w' dL/dw + k' <dL/dv, d>), with w' = -k / 4 and
 * k' = (w - 2 k) / (4 t^2) in closed form (derivatives in t^2), the series' own derivatives below the
 * threshold (as autodiff of the core's series computes them). */

/* o = p q, each as (w, x, y, z) */
#define HAMILTON(T, pw, px, py, pz, qw, qx, qy, qz, ow, ox, oy, oz)                                   \
    const T ow = (pw) * (qw) - ((px) * (qx) + (py) * (qy) + (pz) * (qz));                            \
    const T ox = ((pw) * (qx) + (qw) * (px)) + ((py) * (qz) - (pz) * (qy));                          \
    const T oy = ((pw) * (qy) + (qw) * (py)) + ((pz) * (qx) - (px) * (qz));                          \
    const T oz = ((pw) * (qz) + (qw) * (pz)) + ((px) * (qy) - (py) * (qx))

#define DEFINE_QPLUS(T, SUFFIX, TINY, SQRT, SIN, COS)                                                \
    typedef struct {                                                                                \
        T below, cw[3], ck[3]; /* the threshold in t^2; the series of cos(t/2) and sin(t/2)/t */     \
    } Exp_##SUFFIX;                                                                                 \
                                                                                                    \
    static void exp_table_##SUFFIX(Exp_##SUFFIX *e, const double *table) {                          \
        e->below = (T)table[0];                                                                     \
        for (int i = 0; i < 3; ++i) e->cw[i] = (T)table[1 + i], e->ck[i] = (T)table[4 + i];         \
    }                                                                                               \
                                                                                                    \
    /* _algebra.exp_factors at t2 = t^2: w = cos(t/2), k = sin(t/2)/t; dw, dk their derivatives */ \
    static inline void exp_factors_##SUFFIX(const Exp_##SUFFIX *e, T t2, T *w, T *k, T *dw, T *dk) { \
        const int small = t2 < e->below;                                                            \
        const T tc = small ? (T)1 : t2, angle = SQRT(tc), half = (T)0.5 * angle;                    \
        const T u = small ? t2 : (T)0;                                                              \
        const T ch = COS(half), kc = SIN(half) / angle;                                             \
        *w = small ? e->cw[0] + e->cw[1] * u + e->cw[2] * (u * u) : ch;                             \
        *k = small ? e->ck[0] + e->ck[1] * u + e->ck[2] * (u * u) : kc;                             \
        if (dw != NULL) {                                                                           \
            *dw = small ? e->cw[1] + (T)2 * e->cw[2] * u : (T)-0.25 * kc;                           \
            *dk = small ? e->ck[1] + (T)2 * e->ck[2] * u : (ch - (T)2 * kc) / ((T)4 * tc);          \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    /* _lie._unit: uw .. uz, and scale = 1 / |q| (0 for the zero quaternion) */                    \
    static inline void unit_##SUFFIX(T w, T x, T y, T z, T u[4], T *scale) {                        \
        const T n2 = w * w + x * x + y * y + z * z;                                                 \
        const int zero = n2 < TINY;                                                                 \
        const T aw = w < 0 ? -w : w, ax = x < 0 ? -x : x, ay = y < 0 ? -y : y, az = z < 0 ? -z : z; \
        const T a01 = aw >= ax ? aw : ax, a23 = ay >= az ? ay : az;                                 \
        const T big = zero ? (T)1 : (a01 >= a23 ? a01 : a23);                                       \
        const T sw = w / big, sx = x / big, sy = y / big, sz = z / big;                             \
        const T inv = zero ? (T)0 : (T)1 / SQRT(sw * sw + sx * sx + sy * sy + sz * sz);             \
        u[0] = zero ? (T)1 : sw * inv, u[1] = sx * inv, u[2] = sy * inv, u[3] = sz * inv;           \
        *scale = inv / big;                                                                         \
    }                                                                                               \
                                                                                                    \
    CLONES static void qplus_forward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {      \
        T v[4][BLOCK], d[3][BLOCK], r[4][BLOCK];                                                    \
        Exp_##SUFFIX e;                                                                             \
        exp_table_##SUFFIX(&e, args->series);                                                       \
        const int f = args->first, right = args->right;                                             \
        const T *qw = v[component(f, 0)], *qx = v[component(f, 1)];                                 \
        const T *qy = v[component(f, 2)], *qz = v[component(f, 3)];                                 \
        T *rw = r[component(f, 0)], *rx = r[component(f, 1)];                                       \
        T *ry = r[component(f, 2)], *rz = r[component(f, 3)];                                       \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather4_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            gather3_##SUFFIX(d, (const T *)args->b, args->sb, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                T u[4], scale, w, k;                                                                \
                unit_##SUFFIX(qw[j], qx[j], qy[j], qz[j], u, &scale);                               \
                const T dx = d[0][j], dy = d[1][j], dz = d[2][j];                                   \
                exp_factors_##SUFFIX(&e, dx * dx + dy * dy + dz * dz, &w, &k, NULL, NULL);          \
                const T sx = k * dx, sy = k * dy, sz = k * dz;                                      \
                if (right) {                                                                        \
                    HAMILTON(T, u[0], u[1], u[2], u[3], w, sx, sy, sz, ow, ox, oy, oz);             \
                    rw[j] = ow, rx[j] = ox, ry[j] = oy, rz[j] = oz;                                 \
                } else {                                                                            \
                    HAMILTON(T, w, sx, sy, sz, u[0], u[1], u[2], u[3], ow, ox, oy, oz);             \
                    rw[j] = ow, rx[j] = ox, ry[j] = oy, rz[j] = oz;                                 \
                }                                                                                   \
            }                                                                                       \
            scatter4_##SUFFIX((T *)args->out + 4 * base, r, cnt);                                   \
        }                                                                                           \
    }                                                                                               \
                                                                                                    \
    CLONES static void qplus_backward_##SUFFIX(const Args *args, int64_t begin, int64_t end) {     \
        T v[4][BLOCK], d[3][BLOCK], h[4][BLOCK], r[4][BLOCK], rd[3][BLOCK];                         \
        Exp_##SUFFIX e;                                                                             \
        exp_table_##SUFFIX(&e, args->series);                                                       \
        const int f = args->first, right = args->right;                                             \
        const T *qw = v[component(f, 0)], *qx = v[component(f, 1)];                                 \
        const T *qy = v[component(f, 2)], *qz = v[component(f, 3)];                                 \
        const T *hw = h[component(f, 0)], *hx = h[component(f, 1)];                                 \
        const T *hy = h[component(f, 2)], *hz = h[component(f, 3)];                                 \
        T *rw = r[component(f, 0)], *rx = r[component(f, 1)];                                      \
        T *ry = r[component(f, 2)], *rz = r[component(f, 3)];                                       \
        for (int64_t base = begin; base < end; base += BLOCK) {                                     \
            const int cnt = (int)(end - base < BLOCK ? end - base : BLOCK);                         \
            gather4_##SUFFIX(v, (const T *)args->a, args->sa, base, cnt);                           \
            gather3_##SUFFIX(d, (const T *)args->b, args->sb, base, cnt);                           \
            gather4_##SUFFIX(h, (const T *)args->c, args->sc, base, cnt);                           \
            for (int j = 0; j < cnt; ++j) {                                                         \
                T u[4], scale, w, k, dw, dk;                                                        \
                unit_##SUFFIX(qw[j], qx[j], qy[j], qz[j], u, &scale);                               \
                const T dx = d[0][j], dy = d[1][j], dz = d[2][j];                                   \
                exp_factors_##SUFFIX(&e, dx * dx + dy * dy + dz * dz, &w, &k, &dw, &dk);            \
                const T sx = k * dx, sy = k * dy, sz = k * dz;                                      \
                const T gw = hw[j], gx = hx[j], gy = hy[j], gz = hz[j];                             \
                /* the cotangents of the unit quaternion (a) and of the step (b), or the reverse */ \
                T au[4], as[4];                                                                     \
                if (right) { /* out = u s: g s*, u* g */                                            \
                    HAMILTON(T, gw, gx, gy, gz, w, -sx, -sy, -sz, pw, px, py, pz);                  \
                    HAMILTON(T, u[0], -u[1], -u[2], -u[3], gw, gx, gy, gz, tw, tx, ty, tz);         \
                    au[0] = pw, au[1] = px, au[2] = py, au[3] = pz;                                 \
                    as[0] = tw, as[1] = tx, as[2] = ty, as[3] = tz;                                 \
                } else { /* out = s u: s* g, g u* */                                                \
                    HAMILTON(T, w, -sx, -sy, -sz, gw, gx, gy, gz, pw, px, py, pz);                  \
                    HAMILTON(T, gw, gx, gy, gz, u[0], -u[1], -u[2], -u[3], tw, tx, ty, tz);         \
                    au[0] = pw, au[1] = px, au[2] = py, au[3] = pz;                                 \
                    as[0] = tw, as[1] = tx, as[2] = ty, as[3] = tz;                                 \
                }                                                                                   \
                const T dot = u[0] * au[0] + u[1] * au[1] + u[2] * au[2] + u[3] * au[3];            \
                rw[j] = (au[0] - u[0] * dot) * scale, rx[j] = (au[1] - u[1] * dot) * scale;         \
                ry[j] = (au[2] - u[2] * dot) * scale, rz[j] = (au[3] - u[3] * dot) * scale;         \
                const T c = (T)2 * (as[0] * dw + dk * (as[1] * dx + as[2] * dy + as[3] * dz));      \
                rd[0][j] = k * as[1] + c * dx, rd[1][j] = k * as[2] + c * dy;                       \
                rd[2][j] = k * as[3] + c * dz;                                                      \
            }                                                                                       \
            scatter4_##SUFFIX((T *)args->out + 4 * base, r, cnt);                                   \
            T *out2 = (T *)args->out2 + 3 * base;                                                   \
            for (int j = 0; j < cnt; ++j) {                                                         \
                for (int i = 0; i < 3; ++i) out2[3 * j + i] = rd[i][j];                             \
            }                                                                                       \
        }                                                                                           \
    }

DEFINE_QPLUS(float, f32, FLT_MIN, sqrtf, sinf, cosf)
DEFINE_QPLUS(double, f64, DBL_MIN, sqrt, sin, cos)

/* Kernels by name and dtype (0: float32, 1: float64). */
enum { Q2M_FORWARD, Q2M_BACKWARD, M2Q_FORWARD, M2Q_BACKWARD, JAC_FORWARD, JAC_BACKWARD, QPLUS_FORWARD, QPLUS_BACKWARD };
static const Kernel KERNELS[8][2] = {
    {q2m_forward_f32, q2m_forward_f64},
    {q2m_backward_f32, q2m_backward_f64},
    {m2q_forward_f32, m2q_forward_f64},
    {m2q_backward_f32, m2q_backward_f64},
    {jac_forward_f32, jac_forward_f64},
    {jac_backward_f32, jac_backward_f64},
    {qplus_forward_f32, qplus_forward_f64},
    {qplus_backward_f32, qplus_backward_f64},
};

typedef struct {
    Kernel kernel;
    const Args *args;
    int64_t begin, end;
} Chunk;

static void *run_chunk(void *arg) {
    const Chunk *chunk = (const Chunk *)arg;
    chunk->kernel(chunk->args, chunk->begin, chunk->end);
    return NULL;
}

/* Below this many rows per thread, one thread: starting one costs ~10-30 us, a row ~1-3 ns. */
#define MIN_ROWS_PER_THREAD 32768
#define MAX_THREADS 64

/* Run `kernel` over rows [0, n) on up to `threads` threads (the caller's among them). */
static void run(Kernel kernel, const Args *args, int64_t n, int64_t threads) {
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (threads > n / MIN_ROWS_PER_THREAD) threads = n / MIN_ROWS_PER_THREAD;
    if (threads <= 1) {
        kernel(args, 0, n);
        return;
    }
    Chunk chunks[MAX_THREADS];
    pthread_t ids[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int64_t t = 0; t < threads; ++t) {
        chunks[t] = (Chunk){kernel, args, n * t / threads, n * (t + 1) / threads};
    }
    for (int64_t t = 1; t < threads; ++t) {
        started[t] = pthread_create(&ids[t], NULL, run_chunk, &chunks[t]) == 0;
        if (!started[t]) run_chunk(&chunks[t]); /* no thread to be had: do its share here */
    }
    run_chunk(&chunks[0]);
    for (int64_t t = 1; t < threads; ++t) {
        if (started[t]) pthread_join(ids[t], NULL);
    }
}

#if !defined(DIFFQUAT_KERNELS_ONLY)

/* The Python entry points take integers only (data pointers, strides in elements, sizes, flags),
 * checked for count and type; the Python side guarantees that they describe valid tensors. */
static int read_ints(PyObject *const *argv, Py_ssize_t argc, Py_ssize_t want, const char *name,
                     int64_t *values) {
    if (argc != want) {
        PyErr_Format(PyExc_TypeError, "%s: expected %zd integer arguments, got %zd", name, want, argc);
        return -1;
    }
    for (Py_ssize_t i = 0; i < argc; ++i) {
        values[i] = PyLong_AsLongLong(argv[i]);
        if (values[i] == -1 && PyErr_Occurred()) return -1;
    }
    return 0;
}

static PyObject *launch(Kernel kernel, const Args *args, int64_t n, int64_t threads) {
    Py_BEGIN_ALLOW_THREADS
    run(kernel, args, n, threads);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

#define PTR(v) ((void *)(intptr_t)(v))

/* q2m_forward(dtype, threads, n, first, q, q_row, q_component, out) */
static PyObject *q2m_forward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[8];
    if (read_ints(argv, argc, 8, "q2m_forward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], 0}, .out = PTR(v[7]), .first = (int)v[3]};
    return launch(KERNELS[Q2M_FORWARD][v[0] != 0], &args, v[2], v[1]);
}

/* q2m_backward(dtype, threads, n, first, q, q_row, q_component, grad, grad_row, grad_i, grad_j, out) */
static PyObject *q2m_backward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[12];
    if (read_ints(argv, argc, 12, "q2m_backward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], 0}, .b = PTR(v[7]), .sb = {v[8], v[9], v[10]},
                 .out = PTR(v[11]), .first = (int)v[3]};
    return launch(KERNELS[Q2M_BACKWARD][v[0] != 0], &args, v[2], v[1]);
}

/* m2q_forward(dtype, threads, n, first, m, m_row, m_i, m_j, out) */
static PyObject *m2q_forward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[9];
    if (read_ints(argv, argc, 9, "m2q_forward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], v[7]}, .out = PTR(v[8]), .first = (int)v[3]};
    return launch(KERNELS[M2Q_FORWARD][v[0] != 0], &args, v[2], v[1]);
}

/* m2q_backward(dtype, threads, n, first, m, m_row, m_i, m_j, q, q_row, q_component,
 *              grad, grad_row, grad_component, out) */
static PyObject *m2q_backward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[15];
    if (read_ints(argv, argc, 15, "m2q_backward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], v[7]}, .b = PTR(v[8]), .sb = {v[9], v[10], 0},
                 .c = PTR(v[11]), .sc = {v[12], v[13], 0}, .out = PTR(v[14]), .first = (int)v[3]};
    return launch(KERNELS[M2Q_BACKWARD][v[0] != 0], &args, v[2], v[1]);
}

/* jac_forward(dtype, threads, n, kind, w, w_row, w_component, series, terms0, terms1, terms2, out) */
static PyObject *jac_forward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[12];
    if (read_ints(argv, argc, 12, "jac_forward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], 0}, .series = PTR(v[7]), .terms = {v[8], v[9], v[10]},
                 .out = PTR(v[11]), .first = (int)v[3]};
    return launch(KERNELS[JAC_FORWARD][v[0] != 0], &args, v[2], v[1]);
}

/* jac_backward(dtype, threads, n, kind, w, w_row, w_component, grad, grad_row, grad_i, grad_j,
 *              series, terms0, terms1, terms2, out) */
static PyObject *jac_backward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[16];
    if (read_ints(argv, argc, 16, "jac_backward", v) < 0) return NULL;
    Args args = {.a = PTR(v[4]), .sa = {v[5], v[6], 0}, .b = PTR(v[7]), .sb = {v[8], v[9], v[10]},
                 .series = PTR(v[11]), .terms = {v[12], v[13], v[14]}, .out = PTR(v[15]), .first = (int)v[3]};
    return launch(KERNELS[JAC_BACKWARD][v[0] != 0], &args, v[2], v[1]);
}

/* qplus_forward(dtype, threads, n, first, right, q, q_row, q_component, d, d_row, d_component, table, out) */
static PyObject *qplus_forward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[13];
    if (read_ints(argv, argc, 13, "qplus_forward", v) < 0) return NULL;
    Args args = {.a = PTR(v[5]), .sa = {v[6], v[7], 0}, .b = PTR(v[8]), .sb = {v[9], v[10], 0},
                 .series = PTR(v[11]), .out = PTR(v[12]), .first = (int)v[3], .right = (int)v[4]};
    return launch(KERNELS[QPLUS_FORWARD][v[0] != 0], &args, v[2], v[1]);
}

/* qplus_backward(dtype, threads, n, first, right, q, q_row, q_component, d, d_row, d_component,
 *                grad, grad_row, grad_component, table, out_q, out_d) */
static PyObject *qplus_backward(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[17];
    if (read_ints(argv, argc, 17, "qplus_backward", v) < 0) return NULL;
    Args args = {.a = PTR(v[5]), .sa = {v[6], v[7], 0}, .b = PTR(v[8]), .sb = {v[9], v[10], 0},
                 .c = PTR(v[11]), .sc = {v[12], v[13], 0}, .series = PTR(v[14]), .out = PTR(v[15]),
                 .out2 = PTR(v[16]), .first = (int)v[3], .right = (int)v[4]};
    return launch(KERNELS[QPLUS_BACKWARD][v[0] != 0], &args, v[2], v[1]);
}

/* ---------------------------------------------------------------------------------------------
 * XLA FFI handlers: the same kernels as custom calls of jax programs on the CPU (diffquat/jax/_xla.py
 * registers them and emits the calls).
 *
 * XLA's FFI is a C ABI, versioned and kept binary compatible (jaxlib ships it as
 * xla/ffi/api/c_api.h). The handlers need only the few structures below, declared here so that the
 * extension builds without jax installed (pip builds it in an isolated environment);
 * tests/test_kernels.py compiles them beside the installed jaxlib's header and checks every size
 * and offset. A handler is called with a metadata extension once, to report the API version it was
 * written against, and then at each execution stage; the kernels run at EXECUTE only. The handlers
 * never return an error (NULL is success): the Python side checks dtypes and shapes when it traces,
 * and every buffer XLA passes here is dense, row-major and of the traced shape. */
typedef struct XlaExtension {
    size_t struct_size;
    int type; /* 1: metadata */
    struct XlaExtension *next;
} XlaExtension;

typedef struct {
    size_t struct_size;
    XlaExtension *extension_start;
    int major_version, minor_version;
} XlaApiVersion;

typedef struct {
    size_t struct_size;
    XlaApiVersion api_version;
    uint32_t traits;
} XlaMetadata;

typedef struct {
    XlaExtension extension_base;
    XlaMetadata *metadata;
} XlaMetadataExtension;

typedef struct {
    size_t struct_size;
    XlaExtension *extension_start;
    int dtype; /* 11: F32, 12: F64 */
    void *data;
    int64_t rank;
    int64_t *dims;
} XlaBuffer;

typedef struct { /* the arguments or the results of a call */
    size_t struct_size;
    XlaExtension *extension_start;
    int64_t size;
    int *types;
    void **items; /* XlaBuffer * each: every argument and result here is a buffer */
} XlaList;

typedef struct { /* the leading fields of XLA_FFI_CallFrame, which are all a handler reads */
    size_t struct_size;
    XlaExtension *extension_start;
    const void *api;
    void *ctx;
    int stage; /* 3: EXECUTE */
    XlaList args;
    XlaList rets;
} XlaCallFrame;

enum { XLA_EXTENSION_METADATA = 1, XLA_STAGE_EXECUTE = 3, XLA_F64 = 12 };
/* The bytes of XlaMetadata that a handler writes (up to the traits, without the tail padding). */
#define XLA_METADATA_WRITTEN (offsetof(XlaMetadata, traits) + sizeof(uint32_t))
enum { XLA_API_MAJOR = 0, XLA_API_MINOR = 3 }; /* the version whose layout the structures follow */

/* Threads for a large batch: the processors this process may run on (read once, at import). XLA's
 * CPU runtime runs the custom call on one of its own threads and waits for it. */
static int64_t xla_threads = 1;

static int64_t allowed_processors(void) {
#ifdef CPU_COUNT
    cpu_set_t set;
    if (sched_getaffinity(0, sizeof set, &set) == 0 && CPU_COUNT(&set) > 0) return CPU_COUNT(&set);
#endif
    long online = sysconf(_SC_NPROCESSORS_ONLN);
    return online > 0 ? online : 1;
}

static XlaBuffer *xla_arg(const XlaCallFrame *frame, int i) { return (XlaBuffer *)frame->args.items[i]; }

/* Rows of a buffer whose trailing `trailing` dimensions are one quaternion or one matrix. */
static int64_t xla_rows(const XlaBuffer *buffer, int trailing) {
    int64_t n = 1;
    for (int64_t i = 0; i < buffer->rank - trailing; ++i) n *= buffer->dims[i];
    return n;
}

/* Whether this call is not an execution: the metadata query (answered here) or another stage. */
static int xla_not_executing(XlaCallFrame *frame) {
    XlaExtension *extension = frame->extension_start;
    if (extension != NULL && extension->type == XLA_EXTENSION_METADATA) {
        XlaMetadata *metadata = ((XlaMetadataExtension *)extension)->metadata;
        /* A runtime whose metadata is shorter than the fields written here reads version 0.0 and
         * refuses the handler with a message, where writing past its structure would corrupt it. */
        if (metadata->struct_size >= XLA_METADATA_WRITTEN) {
            metadata->api_version = (XlaApiVersion){sizeof(XlaApiVersion), NULL, XLA_API_MAJOR, XLA_API_MINOR};
            metadata->traits = 0;
        }
        return 1;
    }
    return frame->stage != XLA_STAGE_EXECUTE;
}

static void *xla_ret(const XlaCallFrame *frame, int i) { return ((XlaBuffer *)frame->rets.items[i])->data; }

/* m2q_forward: (matrix) -> q; m2q_backward: (matrix, q, dL/dq) -> dL/dR; q in the handler's order. */
static void *xla_call(XlaCallFrame *frame, int kernel, int first) {
    if (xla_not_executing(frame)) return NULL;
    const XlaBuffer *matrix = xla_arg(frame, 0);
    /* Dense row-major strides in elements: a matrix row is 9 apart, a quaternion row 4. */
    Args args = {.a = matrix->data, .sa = {9, 3, 1}, .out = xla_ret(frame, 0), .first = first};
    if (kernel == M2Q_BACKWARD) {
        args.b = xla_arg(frame, 1)->data, args.sb[0] = 4, args.sb[1] = 1;
        args.c = xla_arg(frame, 2)->data, args.sc[0] = 4, args.sc[1] = 1;
    }
    run(KERNELS[kernel][matrix->dtype == XLA_F64], &args, xla_rows(matrix, 2), xla_threads);
    return NULL;
}

static void *xla_m2q_forward_wxyz(XlaCallFrame *frame) { return xla_call(frame, M2Q_FORWARD, 1); }
static void *xla_m2q_forward_xyzw(XlaCallFrame *frame) { return xla_call(frame, M2Q_FORWARD, 0); }
static void *xla_m2q_backward_wxyz(XlaCallFrame *frame) { return xla_call(frame, M2Q_BACKWARD, 1); }
static void *xla_m2q_backward_xyzw(XlaCallFrame *frame) { return xla_call(frame, M2Q_BACKWARD, 0); }

/* The tables that the torch binding passes with each call (the Jacobians' series, exp_factors'
 * threshold and series), per dtype (0: float32, 1: float64): an XLA handler here takes no attributes,
 * so diffquat/jax/_xla.py hands them over once, at import, before it registers the handlers. */
#define XLA_SERIES_MAX 64
static double xla_series[2][XLA_SERIES_MAX];
static int64_t xla_terms[2][3];
static double xla_exp[2][7];

/* xla_set_tables(f64, series, n_series, terms0, terms1, terms2, exp_table): copies n_series doubles
 * from the address `series` and 7 from `exp_table` (float64 arrays the caller keeps alive for the
 * call), for float32 (f64 = 0) or float64 (f64 = 1). */
static PyObject *xla_set_tables(PyObject *self, PyObject *const *argv, Py_ssize_t argc) {
    (void)self; /* a module function: no instance */
    int64_t v[7];
    if (read_ints(argv, argc, 7, "xla_set_tables", v) < 0) return NULL;
    const int64_t n = v[2], t0 = v[3], t1 = v[4], t2 = v[5];
    /* each series holds 3 to MAX_TERMS coefficients (the kernels differentiate at least 3) */
    const int readable = t0 >= 3 && t1 >= 3 && t2 >= 3 && t0 <= MAX_TERMS && t1 <= MAX_TERMS && t2 <= MAX_TERMS;
    if (v[0] < 0 || v[0] > 1 || !readable || 1 + t0 + t1 + t2 != n || n > XLA_SERIES_MAX) {
        PyErr_SetString(PyExc_ValueError, "xla_set_tables: a table that the kernels cannot read");
        return NULL;
    }
    const double *series = (const double *)PTR(v[1]), *exp_table = (const double *)PTR(v[6]);
    for (int64_t i = 0; i < n; ++i) xla_series[v[0]][i] = series[i];
    xla_terms[v[0]][0] = t0, xla_terms[v[0]][1] = t1, xla_terms[v[0]][2] = t2;
    for (int i = 0; i < 7; ++i) xla_exp[v[0]][i] = exp_table[i];
    Py_RETURN_NONE;
}

/* jac_forward: (w) -> J; jac_backward: (w, dL/dJ) -> dL/dw; `kind` as Args.first. */
static void *xla_jacobian(XlaCallFrame *frame, int kernel, int kind) {
    if (xla_not_executing(frame)) return NULL;
    const XlaBuffer *omega = xla_arg(frame, 0);
    const int f64 = omega->dtype == XLA_F64;
    Args args = {.a = omega->data, .sa = {3, 1, 0}, .out = xla_ret(frame, 0), .first = kind,
                 .series = xla_series[f64], .terms = {xla_terms[f64][0], xla_terms[f64][1], xla_terms[f64][2]}};
    if (kernel == JAC_BACKWARD) args.b = xla_arg(frame, 1)->data, args.sb[0] = 9, args.sb[1] = 3, args.sb[2] = 1;
    run(KERNELS[kernel][f64], &args, xla_rows(omega, 1), xla_threads);
    return NULL;
}

/* qplus_forward: (q, d) -> q exp(d) or exp(d) q; qplus_backward: (q, d, dL/dout) -> (dL/dq, dL/dd);
 * q and d of one batch shape (the Python side broadcasts them), quaternions in the handler's order. */
static void *xla_qplus(XlaCallFrame *frame, int kernel, int first, int right) {
    if (xla_not_executing(frame)) return NULL;
    const XlaBuffer *q = xla_arg(frame, 0);
    const int f64 = q->dtype == XLA_F64;
    Args args = {.a = q->data, .sa = {4, 1, 0}, .b = xla_arg(frame, 1)->data, .sb = {3, 1, 0},
                 .series = xla_exp[f64], .out = xla_ret(frame, 0), .first = first, .right = right};
    if (kernel == QPLUS_BACKWARD) {
        args.c = xla_arg(frame, 2)->data, args.sc[0] = 4, args.sc[1] = 1;
        args.out2 = xla_ret(frame, 1);
    }
    run(KERNELS[kernel][f64], &args, xla_rows(q, 1), xla_threads);
    return NULL;
}

#define XLA_JACOBIAN(NAME, KIND)                                                                     \
    static void *xla_jac_forward_##NAME(XlaCallFrame *f) { return xla_jacobian(f, JAC_FORWARD, KIND); } \
    static void *xla_jac_backward_##NAME(XlaCallFrame *f) { return xla_jacobian(f, JAC_BACKWARD, KIND); }
XLA_JACOBIAN(jl, 0)
XLA_JACOBIAN(jr, 1)
XLA_JACOBIAN(jl_inv, 2)
XLA_JACOBIAN(jr_inv, 3)

#define XLA_QPLUS(ORDER, FIRST, SIDE, RIGHT)                                                         \
    static void *xla_qplus_forward_##ORDER##_##SIDE(XlaCallFrame *f) {                              \
        return xla_qplus(f, QPLUS_FORWARD, FIRST, RIGHT);                                            \
    }                                                                                                \
    static void *xla_qplus_backward_##ORDER##_##SIDE(XlaCallFrame *f) {                             \
        return xla_qplus(f, QPLUS_BACKWARD, FIRST, RIGHT);                                           \
    }
XLA_QPLUS(wxyz, 1, right, 1)
XLA_QPLUS(wxyz, 1, left, 0)
XLA_QPLUS(xyzw, 0, right, 1)
XLA_QPLUS(xyzw, 0, left, 0)

/* xla_handlers(): {name: PyCapsule of the handler}, for jax.ffi.register_ffi_target. */
static PyObject *xla_handlers(PyObject *self, PyObject *unused) {
    (void)self, (void)unused; /* METH_NOARGS */
    static const struct {
        const char *name;
        void *(*handler)(XlaCallFrame *);
    } table[] = {
        {"m2q_forward_wxyz", xla_m2q_forward_wxyz},
        {"m2q_forward_xyzw", xla_m2q_forward_xyzw},
        {"m2q_backward_wxyz", xla_m2q_backward_wxyz},
        {"m2q_backward_xyzw", xla_m2q_backward_xyzw},
#define JAC_ROWS(NAME) {"jac_forward_" #NAME, xla_jac_forward_##NAME}, {"jac_backward_" #NAME, xla_jac_backward_##NAME}
        JAC_ROWS(jl), JAC_ROWS(jr), JAC_ROWS(jl_inv), JAC_ROWS(jr_inv),
#define QPLUS_ROWS(ORDER, SIDE)                                                                      \
    {"qplus_forward_" #ORDER "_" #SIDE, xla_qplus_forward_##ORDER##_##SIDE},                         \
        {"qplus_backward_" #ORDER "_" #SIDE, xla_qplus_backward_##ORDER##_##SIDE}
        QPLUS_ROWS(wxyz, right), QPLUS_ROWS(wxyz, left), QPLUS_ROWS(xyzw, right), QPLUS_ROWS(xyzw, left),
    };
    PyObject *handlers = PyDict_New();
    if (handlers == NULL) return NULL;
    for (size_t i = 0; i < sizeof table / sizeof table[0]; ++i) {
        PyObject *capsule = PyCapsule_New((void *)table[i].handler, NULL, NULL);
        if (capsule == NULL || PyDict_SetItemString(handlers, table[i].name, capsule) < 0) {
            Py_XDECREF(capsule);
            Py_DECREF(handlers);
            return NULL;
        }
        Py_DECREF(capsule);
    }
    return handlers;
}

static PyMethodDef methods[] = {
    {"q2m_forward", (PyCFunction)(void (*)(void))q2m_forward, METH_FASTCALL,
     "quaternion_to_matrix forward over raw buffers (see diffquat/torch/_cpu.py)."},
    {"q2m_backward", (PyCFunction)(void (*)(void))q2m_backward, METH_FASTCALL,
     "quaternion_to_matrix backward over raw buffers."},
    {"m2q_forward", (PyCFunction)(void (*)(void))m2q_forward, METH_FASTCALL,
     "matrix_to_quaternion forward over raw buffers."},
    {"m2q_backward", (PyCFunction)(void (*)(void))m2q_backward, METH_FASTCALL,
     "matrix_to_quaternion backward over raw buffers."},
    {"jac_forward", (PyCFunction)(void (*)(void))jac_forward, METH_FASTCALL,
     "The SO(3) Jacobians and their inverses, forward, over raw buffers."},
    {"jac_backward", (PyCFunction)(void (*)(void))jac_backward, METH_FASTCALL,
     "The SO(3) Jacobians and their inverses, backward, over raw buffers."},
    {"qplus_forward", (PyCFunction)(void (*)(void))qplus_forward, METH_FASTCALL,
     "quaternion_plus forward over raw buffers."},
    {"qplus_backward", (PyCFunction)(void (*)(void))qplus_backward, METH_FASTCALL,
     "quaternion_plus backward over raw buffers."},
    {"xla_handlers", xla_handlers, METH_NOARGS,
     "The kernels as XLA FFI handlers: {name: PyCapsule} (see diffquat/jax/_xla.py)."},
    {"xla_set_tables", (PyCFunction)(void (*)(void))xla_set_tables, METH_FASTCALL,
     "The series tables of the XLA handlers of the Jacobians and quaternion_plus, per dtype."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_kernels",
    .m_doc = "quaternion_to_matrix, matrix_to_quaternion, the SO(3) Jacobians and quaternion_plus on the "
             "CPU, one pass each way (_kernels.c).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__kernels(void) {
    xla_threads = allowed_processors();
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
#if defined(DIFFQUAT_PORTABLE)
    const long portable = 1;
#else
    const long portable = 0;
#endif
    /* PORTABLE: 1 for the scalar build of the tests, 0 for the installed one */
    if (PyModule_AddIntConstant(m, "PORTABLE", portable) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}

#endif /* !DIFFQUAT_KERNELS_ONLY */
