/*
 * dqm tile kernel: the per-element work of one block of the all-pairs pass.
 *
 * Given a tile G of squared distances (float32, m target rows x k contributor
 * columns, row stride ldg), per-column kernel weights w and on/off factors s, it
 *   - adds to dens[r] the kernel terms sum_c s_c K(G[r, c] w_c) (the self term, if the
 *     tile holds it, is left out: the caller adds exactly 1 for it),
 *   - adds to err[r] sum_c |dK_c/d(d2)|, which times the error of a squared
 *     distance bounds the error of dens[r],
 *   - appends every (r, c) with G[r, c] < rad2[r] (candidate tree edges).
 *
 * Plain C, no Python API: loaded with ctypes (dqm/core/native.py), which
 * releases the GIL during the call so tiles run in parallel threads. The same
 * computation in numpy lives beside it and the tests check they agree.
 *
 * exp(-t) is a Cephes-style polynomial (error ~2 ulp in float32). On x86-64
 * CPUs with AVX-512 (F, DQ) or AVX2+FMA (checked at run time) the row loops use
 * those intrinsics; elsewhere the portable scalar loops run.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include <float.h>

#define KERNEL_GAUSSIAN 0
#define KERNEL_QUADRATIC 1

#if defined(__GNUC__) && defined(__x86_64__)
#define DQM_HAVE_AVX2_PATH 1
#include <immintrin.h>
#endif

/* Cephes expf coefficients */
#define EXP_C0 1.9875691500e-4f
#define EXP_C1 1.3981999507e-3f
#define EXP_C2 8.3334519073e-3f
#define EXP_C3 4.1665795894e-2f
#define EXP_C4 1.6666665459e-1f
#define EXP_C5 5.0000001201e-1f
#define LOG2E 1.44269504088896341f
#define LN2_HI 0.693359375f
#define LN2_LO -2.12194440e-4f

static inline float exp_neg(float t)
{
    /* exp(-t) for t in [0, 87] */
    float x = -t;
    float rn = nearbyintf(x * LOG2E);
    float r = x - rn * LN2_HI;
    r = r - rn * LN2_LO;
    float p = EXP_C0;
    p = p * r + EXP_C1;
    p = p * r + EXP_C2;
    p = p * r + EXP_C3;
    p = p * r + EXP_C4;
    p = p * r + EXP_C5;
    p = p * r * r + r + 1.0f;
    union { int32_t i; float f; } scale;
    scale.i = ((int32_t)rn + 127) << 23;
    return p * scale.f;
}

/* Row sums over columns [0, k): kernel terms, error weights, and the number of
   columns with g < lim, or, when rad2c is given, with g < lim or g < rad2c[c]
   (the candidate test of a symmetric tile, so that only rows that hold a
   candidate are scanned again). */
typedef struct { float acc, err; int64_t hits; } RowOut;

/* Every float32 sum of kernel terms runs in partial sums of at most
   SUM_CHAIN sequential additions (16 lanes or accumulators over a row of at
   most 1024 columns; column sums flushed to float64 every SUM_CHAIN rows), and
   the partials are combined in at most 16 more: a term is rounded at most
   SUM_ROUNDINGS times before it reaches float64. The caller's error bound
   (dqm/core/pairs.py) reads this number. */
#define SUM_CHAIN 64
#define SUM_ROUNDINGS (SUM_CHAIN + 16 + 2)
#define MAX_ROW 1024

/* The contract between this file and dqm/core/native.py (entry points, their arguments, the buffers the caller
   makes): native.py loads a kernel only of its own KERNEL_VERSION, so a build older than the Python beside it
   (a checkout updated without a new install) is never called with buffers it would write past. Raise it with
   any such change, here and in native.py. */
int32_t dqm_kernel_version(void)
{
    return 2;
}

int32_t dqm_sum_roundings(void)
{
    return SUM_ROUNDINGS;
}

static RowOut row_scalar(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim,
                         const float *rad2c)
{
    float acc[16] = {0}, err[16] = {0};
    RowOut o = {0.0f, 0.0f, 0};
    for (int64_t c = 0; c < k; ++c) {
        float d2 = g[c] < 0.0f ? 0.0f : g[c];
        float t = d2 * w[c];
        int l = (int)(c & 15);
        if (kernel == KERNEL_GAUSSIAN) {
            if (t > 87.0f) t = 87.0f;
            float e = exp_neg(t) * s[c];
            acc[l] += e;
            err[l] += e * w[c];
        } else {
            float q = 1.0f - t;
            if (q > 0.0f) acc[l] += q * s[c];
            if (q > -0.01f) err[l] += w[c] * s[c];
        }
        o.hits += g[c] < lim || (rad2c && g[c] < rad2c[c]);
    }
    for (int l = 0; l < 16; ++l) {
        o.acc += acc[l];
        o.err += err[l];
    }
    return o;
}

#ifdef DQM_HAVE_AVX2_PATH
__attribute__((target("avx2,fma")))
static inline float hsum8(__m256 v)
{
    __m128 lo = _mm256_castps256_ps128(v), hi = _mm256_extractf128_ps(v, 1);
    lo = _mm_add_ps(lo, hi);
    lo = _mm_hadd_ps(lo, lo);
    lo = _mm_hadd_ps(lo, lo);
    return _mm_cvtss_f32(lo);
}

__attribute__((target("avx2,fma")))
static inline __m256 exp_neg8(__m256 t)
{
    __m256 x = _mm256_sub_ps(_mm256_setzero_ps(), t);
    __m256 rn = _mm256_round_ps(_mm256_mul_ps(x, _mm256_set1_ps(LOG2E)),
                                _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m256 r = _mm256_fnmadd_ps(rn, _mm256_set1_ps(LN2_HI), x);
    r = _mm256_fnmadd_ps(rn, _mm256_set1_ps(LN2_LO), r);
    __m256 p = _mm256_set1_ps(EXP_C0);
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(EXP_C1));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(EXP_C2));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(EXP_C3));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(EXP_C4));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(EXP_C5));
    p = _mm256_fmadd_ps(_mm256_mul_ps(p, r), r, _mm256_add_ps(r, _mm256_set1_ps(1.0f)));
    __m256i n = _mm256_cvtps_epi32(rn);
    __m256i e = _mm256_slli_epi32(_mm256_add_epi32(n, _mm256_set1_epi32(127)), 23);
    return _mm256_mul_ps(p, _mm256_castsi256_ps(e));
}

__attribute__((target("avx2,fma")))
static RowOut row_avx2(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim,
                       const float *rad2c)
{
    /* two accumulators (columns c..c+7 and c+8..c+15): chains of k / 16 */
    __m256 acc[2] = {_mm256_setzero_ps(), _mm256_setzero_ps()}, err[2] = {_mm256_setzero_ps(), _mm256_setzero_ps()};
    __m256 zero = _mm256_setzero_ps(), vmax = _mm256_set1_ps(87.0f), one = _mm256_set1_ps(1.0f);
    __m256 edge = _mm256_set1_ps(-0.01f), vlim = _mm256_set1_ps(lim);
    int64_t hits = 0;
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        int l = (int)((c >> 3) & 1);
        __m256 gv = _mm256_loadu_ps(g + c);
        __m256 wv = _mm256_loadu_ps(w + c);
        __m256 sv = _mm256_loadu_ps(s + c);
        __m256 t = _mm256_mul_ps(_mm256_max_ps(gv, zero), wv);
        if (kernel == KERNEL_GAUSSIAN) {
            __m256 e = _mm256_mul_ps(exp_neg8(_mm256_min_ps(t, vmax)), sv);
            acc[l] = _mm256_add_ps(acc[l], e);
            err[l] = _mm256_fmadd_ps(e, wv, err[l]);
        } else {
            __m256 q = _mm256_sub_ps(one, t);
            acc[l] = _mm256_add_ps(acc[l], _mm256_mul_ps(_mm256_max_ps(q, zero), sv));
            __m256 near = _mm256_and_ps(_mm256_cmp_ps(q, edge, _CMP_GT_OQ), _mm256_mul_ps(wv, sv));
            err[l] = _mm256_add_ps(err[l], near);
        }
        __m256 in = _mm256_cmp_ps(gv, vlim, _CMP_LT_OQ);
        if (rad2c)
            in = _mm256_or_ps(in, _mm256_cmp_ps(gv, _mm256_loadu_ps(rad2c + c), _CMP_LT_OQ));
        hits += __builtin_popcount(_mm256_movemask_ps(in));
    }
    RowOut tail = row_scalar(kernel, g + c, w + c, s + c, k - c, lim, rad2c ? rad2c + c : 0);
    RowOut o;
    o.acc = hsum8(_mm256_add_ps(acc[0], acc[1])) + tail.acc;
    o.err = hsum8(_mm256_add_ps(err[0], err[1])) + tail.err;
    o.hits = hits + tail.hits;
    return o;
}
#endif

#ifdef DQM_HAVE_AVX2_PATH
/* AVX-512: 16 lanes, masked tails, and the row and column directions of a
   symmetric tile in one loop (each distance is loaded once). exp_neg16 is
   exp_neg8 lane for lane (scalef multiplies by 2^rn exactly, as the exponent
   trick does for rn >= -126, which the clamp at 87 guarantees), so both paths
   compute the same terms; only the order of the float32 sums differs. */
#define AVX512_TARGET __attribute__((target("avx512f,avx512dq,avx2,fma")))

AVX512_TARGET
static inline __m512 exp_neg16(__m512 t)
{
    __m512 x = _mm512_sub_ps(_mm512_setzero_ps(), t);
    __m512 rn = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(LOG2E)),
                                     _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m512 r = _mm512_fnmadd_ps(rn, _mm512_set1_ps(LN2_HI), x);
    r = _mm512_fnmadd_ps(rn, _mm512_set1_ps(LN2_LO), r);
    __m512 p = _mm512_set1_ps(EXP_C0);
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(EXP_C1));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(EXP_C2));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(EXP_C3));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(EXP_C4));
    p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(EXP_C5));
    p = _mm512_fmadd_ps(_mm512_mul_ps(p, r), r, _mm512_add_ps(r, _mm512_set1_ps(1.0f)));
    return _mm512_scalef_ps(p, rn);
}

static inline __mmask16 tail_mask(int64_t left)
{
    return left >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << left) - 1u);
}

/* Kernel terms of the squared distances d2 (>= 0) scaled by w, times s, and the
   error weights; the tail lanes have s == 0 (masked loads), so they add 0. */
AVX512_TARGET
static inline void terms16(int kernel, __m512 d2, __m512 w, __m512 s, __m512 *acc, __m512 *err)
{
    __m512 t = _mm512_mul_ps(d2, w);
    if (kernel == KERNEL_GAUSSIAN) {
        __m512 e = _mm512_mul_ps(exp_neg16(_mm512_min_ps(t, _mm512_set1_ps(87.0f))), s);
        *acc = _mm512_add_ps(*acc, e);
        *err = _mm512_fmadd_ps(e, w, *err);
    } else {
        __m512 q = _mm512_sub_ps(_mm512_set1_ps(1.0f), t);
        *acc = _mm512_fmadd_ps(_mm512_max_ps(q, _mm512_setzero_ps()), s, *acc);
        __mmask16 near = _mm512_cmp_ps_mask(q, _mm512_set1_ps(-0.01f), _CMP_GT_OQ);
        *err = _mm512_mask_add_ps(*err, near, *err, _mm512_mul_ps(w, s));
    }
}

AVX512_TARGET
static RowOut row_avx512(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim)
{
    /* the diagonal tile's rows only: hits count g < lim */
    __m512 acc = _mm512_setzero_ps(), err = _mm512_setzero_ps();
    __m512 vlim = _mm512_set1_ps(lim);
    int64_t hits = 0;
    for (int64_t c = 0; c < k; c += 16) {
        __mmask16 m = tail_mask(k - c);
        __m512 gv = _mm512_maskz_loadu_ps(m, g + c);
        terms16(kernel, _mm512_max_ps(gv, _mm512_setzero_ps()), _mm512_maskz_loadu_ps(m, w + c),
                _mm512_maskz_loadu_ps(m, s + c), &acc, &err);
        hits += __builtin_popcount(_mm512_mask_cmp_ps_mask(m, gv, vlim, _CMP_LT_OQ));
    }
    RowOut o = {_mm512_reduce_add_ps(acc), _mm512_reduce_add_ps(err), hits};
    return o;
}

/* One row r of a symmetric tile, both directions: the row's sums over the
   columns (weights wc, sc) and every column's sums over this row (weight wr,
   on/off sr) added to cacc / cerr; hits counts the candidates, g < lim or
   g < rad2c[c]. */
AVX512_TARGET
static RowOut rowcol_avx512(int kernel, const float *g, const float *wc, const float *sc, float wr, float sr,
                            int64_t k, float lim, const float *rad2c, float *cacc, float *cerr)
{
    __m512 acc = _mm512_setzero_ps(), err = _mm512_setzero_ps();
    __m512 vlim = _mm512_set1_ps(lim), wrv = _mm512_set1_ps(wr), srv = _mm512_set1_ps(sr);
    int64_t hits = 0;
    for (int64_t c = 0; c < k; c += 16) {
        __mmask16 m = tail_mask(k - c);
        __m512 gv = _mm512_maskz_loadu_ps(m, g + c);
        __m512 d2 = _mm512_max_ps(gv, _mm512_setzero_ps());
        terms16(kernel, d2, _mm512_maskz_loadu_ps(m, wc + c), _mm512_maskz_loadu_ps(m, sc + c), &acc, &err);
        __m512 ca = _mm512_maskz_loadu_ps(m, cacc + c), ce = _mm512_maskz_loadu_ps(m, cerr + c);
        terms16(kernel, d2, wrv, srv, &ca, &ce);
        _mm512_mask_storeu_ps(cacc + c, m, ca);
        _mm512_mask_storeu_ps(cerr + c, m, ce);
        __mmask16 in = _mm512_mask_cmp_ps_mask(m, gv, vlim, _CMP_LT_OQ)
                     | _mm512_mask_cmp_ps_mask(m, gv, _mm512_maskz_loadu_ps(m, rad2c + c), _CMP_LT_OQ);
        hits += __builtin_popcount(in);
    }
    RowOut o = {_mm512_reduce_add_ps(acc), _mm512_reduce_add_ps(err), hits};
    return o;
}
#endif

/* Which loops run: 3 AVX-512 with VNNI (uint8 distances by integer dot products), 2 AVX-512,
   1 AVX2, 0 portable C; resolved once from the CPU, and capped by dqm_set_simd_level (tests
   run every level the CPU has). */
static int simd_level = -1;

static void resolve_simd(void)
{
    if (simd_level >= 0)
        return;
    int level = 0;
#ifdef DQM_HAVE_AVX2_PATH
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) {
        level = 1;
        if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq")) {
            level = 2;
            if (__builtin_cpu_supports("avx512vnni") && __builtin_cpu_supports("avx512bw"))
                level = 3;
        }
    }
#endif
    simd_level = level;
}

static RowOut row_terms(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim,
                        const float *rad2c)
{
    resolve_simd();
#ifdef DQM_HAVE_AVX2_PATH
    if (simd_level >= 2 && !rad2c)
        return row_avx512(kernel, g, w, s, k, lim);
    if (simd_level >= 1)
        return row_avx2(kernel, g, w, s, k, lim, rad2c);
#endif
    return row_scalar(kernel, g, w, s, k, lim, rad2c);
}

/* Which loops run (see simd_level). */
int32_t dqm_simd_level(void)
{
    resolve_simd();
    return simd_level;
}

/* Use at most the given level (never more than the CPU has); returns the level now in use. */
int32_t dqm_set_simd_level(int32_t cap)
{
    simd_level = -1;
    resolve_simd();
    if (cap < simd_level)
        simd_level = cap < 0 ? 0 : cap;
    return simd_level;
}

/* Column direction of a symmetric tile: for one row r (contributor with weight
   wr, on/off sr) add its kernel terms to every column's sums. */
static void col_scalar(int kernel, const float *g, float wr, float sr, int64_t k,
                       float *cacc, float *cerr)
{
    for (int64_t c = 0; c < k; ++c) {
        float d2 = g[c] < 0.0f ? 0.0f : g[c];
        float t = d2 * wr;
        if (kernel == KERNEL_GAUSSIAN) {
            if (t > 87.0f) t = 87.0f;
            float e = exp_neg(t) * sr;
            cacc[c] += e;
            cerr[c] += e * wr;
        } else {
            float q = 1.0f - t;
            if (q > 0.0f) cacc[c] += q * sr;
            if (q > -0.01f) cerr[c] += wr * sr;
        }
    }
}

#ifdef DQM_HAVE_AVX2_PATH
__attribute__((target("avx2,fma")))
static void col_avx2(int kernel, const float *g, float wr, float sr, int64_t k,
                     float *cacc, float *cerr)
{
    __m256 wv = _mm256_set1_ps(wr), sv = _mm256_set1_ps(sr), wsv = _mm256_set1_ps(wr * sr);
    __m256 zero = _mm256_setzero_ps(), vmax = _mm256_set1_ps(87.0f), one = _mm256_set1_ps(1.0f);
    __m256 edge = _mm256_set1_ps(-0.01f);
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        __m256 gv = _mm256_loadu_ps(g + c);
        __m256 t = _mm256_mul_ps(_mm256_max_ps(gv, zero), wv);
        __m256 a = _mm256_loadu_ps(cacc + c), e = _mm256_loadu_ps(cerr + c);
        if (kernel == KERNEL_GAUSSIAN) {
            __m256 x = _mm256_mul_ps(exp_neg8(_mm256_min_ps(t, vmax)), sv);
            a = _mm256_add_ps(a, x);
            e = _mm256_fmadd_ps(x, wv, e);
        } else {
            __m256 q = _mm256_sub_ps(one, t);
            a = _mm256_add_ps(a, _mm256_mul_ps(_mm256_max_ps(q, zero), sv));
            e = _mm256_add_ps(e, _mm256_and_ps(_mm256_cmp_ps(q, edge, _CMP_GT_OQ), wsv));
        }
        _mm256_storeu_ps(cacc + c, a);
        _mm256_storeu_ps(cerr + c, e);
    }
    col_scalar(kernel, g + c, wr, sr, k - c, cacc + c, cerr + c);
}
#endif

static void col_terms(int kernel, const float *g, float wr, float sr, int64_t k, float *cacc, float *cerr)
{
#ifdef DQM_HAVE_AVX2_PATH
    if (simd_level >= 1)
        return col_avx2(kernel, g, wr, sr, k, cacc, cerr);
#endif
    col_scalar(kernel, g, wr, sr, k, cacc, cerr);
}

/*
 * Symmetric off-diagonal tile: rows and columns are disjoint feature sets, the
 * tile is computed once and used both ways. Row r's density gets the terms of
 * the columns (weights wc, sc); column c's density gets the terms of the rows
 * (weights wr, sr). Candidate pairs: g < max(rad2r[r], rad2c[c]) (either end
 * as the child). cacc/cerr are float scratch of length k. Returns the count of
 * pairs written, -1 if more than cap, or -2 if k > MAX_ROW.
 */
int64_t dqm_tile_sym(const float *G, int64_t m, int64_t k, int64_t ldg,
                     const float *wc, const float *sc, const float *wr, const float *sr,
                     int32_t kernel, const float *rad2r, const float *rad2c,
                     double *dens_r, double *err_r, double *dens_c, double *err_c,
                     float *cacc, float *cerr,
                     int32_t *cand_r, int32_t *cand_c, int64_t cap)
{
    int64_t count = 0;
    if (k > MAX_ROW)
        return -2; /* the sums' error bound assumes rows of at most MAX_ROW columns */
    resolve_simd();
    for (int64_t c = 0; c < k; ++c) {
        cacc[c] = 0.0f;
        cerr[c] = 0.0f;
    }
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        float lim = rad2r[r];
        RowOut a;
#ifdef DQM_HAVE_AVX2_PATH
        if (simd_level >= 2) {
            a = rowcol_avx512(kernel, g, wc, sc, wr[r], sr[r], k, lim, rad2c, cacc, cerr);
        } else
#endif
        {
            a = row_terms(kernel, g, wc, sc, k, lim, rad2c);
            col_terms(kernel, g, wr[r], sr[r], k, cacc, cerr);
        }
        dens_r[r] += (double)a.acc;
        err_r[r] += (double)a.err;
        if ((r + 1) % SUM_CHAIN == 0 || r + 1 == m) {
            for (int64_t c = 0; c < k; ++c) {
                dens_c[c] += (double)cacc[c];
                err_c[c] += (double)cerr[c];
                cacc[c] = 0.0f;
                cerr[c] = 0.0f;
            }
        }
        if (a.hits > 0) {
            float lr = rad2r[r];
            for (int64_t c = 0; c < k; ++c) {
                if (g[c] < lr || g[c] < rad2c[c]) {
                    if (count >= cap)
                        return -1;
                    cand_r[count] = (int32_t)r;
                    cand_c[count] = (int32_t)c;
                    ++count;
                }
            }
        }
    }
    return count;
}

#ifdef DQM_HAVE_AVX2_PATH
/* The vector part of near_row: blocks of 8 columns; returns the first column left for the
   scalar loop (*count = -1 when past cap). */
__attribute__((target("avx2,fma")))
static int64_t near_row_avx2(const float *g, int64_t k, float lr, const float *climit, int32_t r,
                             int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t *count, int64_t cap)
{
    __m256 vl = _mm256_set1_ps(lr), vmax = _mm256_set1_ps(FLT_MAX);
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        __m256 v = _mm256_loadu_ps(g + c);
        __m256 in = _mm256_or_ps(_mm256_cmp_ps(v, vl, _CMP_LE_OQ), _mm256_cmp_ps(v, _mm256_loadu_ps(climit + c), _CMP_LE_OQ));
        int mask = _mm256_movemask_ps(_mm256_and_ps(in, _mm256_cmp_ps(v, vmax, _CMP_LT_OQ)));
        while (mask) {
            int l = __builtin_ctz(mask);
            mask &= mask - 1;
            if (*count >= cap) {
                *count = -1;
                return k;
            }
            cand_r[*count] = r;
            cand_c[*count] = (int32_t)(c + l);
            cand_g[*count] = g[c + l];
            ++*count;
        }
    }
    return c;
}
#endif

/* Row minimum of g[0..k) and running column minima cmin[0..k). */
static float minrow_scalar(const float *g, int64_t k, float *cmin)
{
    float mn = FLT_MAX;
    for (int64_t c = 0; c < k; ++c) {
        float v = g[c];
        mn = v < mn ? v : mn;
        cmin[c] = v < cmin[c] ? v : cmin[c];
    }
    return mn;
}

#ifdef DQM_HAVE_AVX2_PATH
__attribute__((target("avx2,fma")))
static float minrow_avx2(const float *g, int64_t k, float *cmin)
{
    __m256 m = _mm256_set1_ps(FLT_MAX);
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        __m256 v = _mm256_loadu_ps(g + c);
        m = _mm256_min_ps(m, v);
        _mm256_storeu_ps(cmin + c, _mm256_min_ps(v, _mm256_loadu_ps(cmin + c)));
    }
    float buf[8];
    _mm256_storeu_ps(buf, m);
    float mn = minrow_scalar(g + c, k - c, cmin + c);
    for (int l = 0; l < 8; ++l)
        mn = buf[l] < mn ? buf[l] : mn;
    return mn;
}
#endif

/* A row's minimum, lowering cmin column by column (the loops of the CPU's level). */
static float minrow(const float *g, int64_t k, float *cmin)
{
#ifdef DQM_HAVE_AVX2_PATH
    if (simd_level >= 1)
        return minrow_avx2(g, k, cmin);
#endif
    return minrow_scalar(g, k, cmin);
}

/* Appends the columns c of row r with g[c] < FLT_MAX and (g[c] <= lr or g[c] <= climit[c]), in
   column order; vector compares skip the blocks with none. Returns the new count, -1 past cap. */
static int64_t near_row(const float *g, int64_t k, float lr, const float *climit, int32_t r,
                        int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t count, int64_t cap)
{
    int64_t c = 0;
#ifdef DQM_HAVE_AVX2_PATH
    if (simd_level >= 1)
        c = near_row_avx2(g, k, lr, climit, r, cand_r, cand_c, cand_g, &count, cap);
    if (count < 0)
        return -1;
#endif
    for (; c < k; ++c) {
        float v = g[c];
        if (v < FLT_MAX && (v <= lr || v <= climit[c])) {
            if (count >= cap)
                return -1;
            cand_r[count] = r;
            cand_c[count] = (int32_t)c;
            cand_g[count] = v;
            ++count;
        }
    }
    return count;
}

/*
 * Nearest-neighbour tile of the distinctiveness pass: rows and columns are
 * features of one image (pass a tile whose self pairs are set to FLT_MAX;
 * entries equal to FLT_MAX are never reported).
 * Writes every row's and column's minimum over the tile and every (r, c) with
 * g <= rmin[r] + slack_r[r] or g <= cmin[c] + slack_c[c] (with its value), so
 * that the caller, knowing the global minima, can recompute those exactly;
 * with slack_r NULL the minima only (where they are exact: integer descriptors).
 * Returns the count, -1 if more than cap, or -2 if k > MAX_ROW.
 */
int64_t dqm_nearest_sym(const float *G, int64_t m, int64_t k, int64_t ldg,
                        const float *slack_r, const float *slack_c,
                        float *rmin, float *cmin,
                        int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t cap)
{
    if (k > MAX_ROW)
        return -2;
    resolve_simd();
    for (int64_t c = 0; c < k; ++c)
        cmin[c] = FLT_MAX;
    for (int64_t r = 0; r < m; ++r)
        rmin[r] = minrow(G + r * ldg, k, cmin);
    if (slack_r == NULL)
        return 0;
    float climit[MAX_ROW]; /* column limits once */
    for (int64_t c = 0; c < k; ++c)
        climit[c] = cmin[c] + slack_c[c];
    int64_t count = 0;
    for (int64_t r = 0; r < m; ++r) {
        count = near_row(G + r * ldg, k, rmin[r] + slack_r[r], climit, (int32_t)r, cand_r, cand_c, cand_g,
                         count, cap);
        if (count < 0)
            return -1;
    }
    return count;
}

/*
 * self_col: for row r the column holding the same feature is r + self_col when
 * 0 <= r + self_col < k (pass a value <= -m or >= k when the tile holds no
 * self pair). Returns the number of candidate pairs written, -1 when more
 * than cap were found (the caller retries the tile with a larger buffer), or
 * -2 if k > MAX_ROW.
 */
int64_t dqm_tile(const float *G, int64_t m, int64_t k, int64_t ldg,
                 const float *w, const float *s, int32_t kernel, const float *rad2,
                 int64_t self_col, double *dens, double *err,
                 int32_t *cand_r, int32_t *cand_c, int64_t cap)
{
    int64_t count = 0;
    if (k > MAX_ROW)
        return -2;
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        float lim = rad2[r];
        int64_t sc = r + self_col;
        int has_self = (sc >= 0 && sc < k);
        /* the self column is skipped, not subtracted: subtracting ~1 from a
           float sum would lose the small terms of isolated features */
        RowOut a = row_terms(kernel, g, w, s, has_self ? sc : k, lim, 0);
        if (has_self) {
            RowOut b = row_terms(kernel, g + sc + 1, w + sc + 1, s + sc + 1, k - sc - 1, lim, 0);
            a.acc += b.acc;
            a.err += b.err;
            a.hits += b.hits;
        }
        dens[r] += (double)a.acc;
        err[r] += (double)a.err;
        if (a.hits > 0) {
            for (int64_t c = 0; c < k; ++c) {
                if (g[c] < lim && c != sc) {
                    if (count >= cap)
                        return -1;
                    cand_r[count] = (int32_t)r;
                    cand_c[count] = (int32_t)c;
                    ++count;
                }
            }
        }
    }
    return count;
}

/*
 * Any-within scan of a tile of squared distances (the lower-bound sketch
 * pre-filter of dqm/distributed/sketch.py): sets hit[r] = 1 when some column c
 * has G[r, c] < max(rad2r[r], rad2c[c]). Rows already hit are skipped and a
 * row stops at its first hit, checked every 64 columns so the inner loop
 * vectorises.
 */
void dqm_any_within(const float *G, int64_t m, int64_t k, int64_t ldg,
                    const float *rad2r, const float *rad2c, uint8_t *hit)
{
    for (int64_t r = 0; r < m; ++r) {
        if (hit[r])
            continue;
        const float *g = G + r * ldg;
        const float lr = rad2r[r];
        for (int64_t c0 = 0; c0 < k; c0 += 64) {
            int64_t c1 = c0 + 64 < k ? c0 + 64 : k;
            int any = 0;
            for (int64_t c = c0; c < c1; ++c) {
                float lim = rad2c[c] > lr ? rad2c[c] : lr;
                any |= g[c] < lim;
            }
            if (any) {
                hit[r] = 1;
                break;
            }
        }
    }
}

/*
 * Rank relation of candidate c to child j from density intervals [lo, hi]
 * (float64, rigorous): 1 if c certainly ranks above j, -1 if certainly below,
 * 0 if the intervals overlap and the exact densities must decide. Two exact
 * (degenerate) equal intervals are certain: equal densities rank by index.
 */
static inline int rank_relation(const double *lo, const double *hi, int64_t c, int64_t j)
{
    if (lo[c] > hi[j])
        return 1;
    if (hi[c] < lo[j])
        return -1;
    if (lo[c] == hi[c] && lo[j] == hi[j])
        return c < j ? 1 : -1;
    return 0;
}

/* One (child, candidate) pair at squared distance v of the parent tile: a
   certainly higher-ranked candidate lowers the child's tile minimum *tmin and
   is written when v <= min(lim, *tmin + slack); an uncertain one is always
   written. Returns -1 when the output is full. */
static inline int consider(const double *lo, const double *hi, int64_t child, int64_t cand, float v,
                           float *tmin, float lim, float slack,
                           int64_t *out_child, int64_t *out_cand, float *out_g, int64_t *count, int64_t cap)
{
    int rel = rank_relation(lo, hi, cand, child);
    if (rel < 0)
        return 0;
    if (rel > 0) {
        if (v < *tmin)
            *tmin = v;
        if (*tmin + slack < lim)
            lim = *tmin + slack;
        if (v > lim)
            return 0;
    }
    if (*count >= cap)
        return -1;
    out_child[*count] = child;
    out_cand[*count] = cand;
    out_g[*count] = v;
    ++*count;
    return 0;
}

/*
 * Parent tile of the streaming parent pass (memory O(n) whatever rho is).
 *
 * G holds squared distances (float32, rows: features ra..ra+m, columns:
 * cb..cb+k, row stride ldg). For each child (a row, and on an off-diagonal
 * tile also a column) and each candidate within the child's radius
 * (g < rad2 of the child) that is not in the child's image when img is given:
 *   - a candidate that certainly ranks above the child lowers the child's
 *     tile minimum (rmin / cmin, FLT_MAX when there is none) and is written
 *     out when g <= min(lim_child, running tile minimum + slack_child);
 *   - a candidate whose rank is uncertain is always written out (the caller
 *     settles it with exact densities).
 * lim_* are the caller's current global limits (best so far + slack), so
 * nothing is written that cannot become the child's nearest higher-ranked
 * candidate. diag != 0: rows and columns are the same features (ra == cb);
 * only the row direction runs and the self pair is skipped.
 * Writes (child, cand, g) with global indices; returns the count or -1 when
 * more than cap.
 */
int64_t dqm_parent_tile(const float *G, int64_t m, int64_t k, int64_t ldg,
                        int64_t ra, int64_t cb, int32_t diag,
                        const double *lo, const double *hi, const int32_t *img,
                        const float *rad2r, const float *rad2c,
                        const float *limr, const float *limc,
                        const float *slackr, const float *slackc,
                        float *rmin, float *cmin,
                        int64_t *out_child, int64_t *out_cand, float *out_g, int64_t cap)
{
    int64_t count = 0;
    for (int64_t c = 0; c < k; ++c)
        cmin[c] = FLT_MAX;
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        const int64_t jr = ra + r;
        const float lr = rad2r[r];
        float best_r = FLT_MAX;
        for (int64_t c = 0; c < k; ++c) {
            const float v = g[c];
            const int64_t jc = cb + c;
            const int as_row = v < lr;
            const int as_col = !diag && v < rad2c[c];
            if (!(as_row || as_col))
                continue;
            if (diag && c == r)
                continue;
            if (img && img[jr] == img[jc])
                continue;
            if (as_row && consider(lo, hi, jr, jc, v, &best_r, limr[r], slackr[r],
                                   out_child, out_cand, out_g, &count, cap) < 0)
                return -1;
            if (as_col && consider(lo, hi, jc, jr, v, &cmin[c], limc[c], slackc[c],
                                   out_child, out_cand, out_g, &count, cap) < 0)
                return -1;
        }
        rmin[r] = best_r;
    }
    return count;
}

/*
 * Integer squared distances with AVX-512 VNNI, for uint8 descriptors: vpdpbusd sums 64 byte
 * products per instruction, four times the multiply-adds of an AVX2 float32 FMA.
 */
#ifdef DQM_HAVE_AVX2_PATH
#define VNNI_TARGET __attribute__((target("avx512f,avx512vnni,avx512bw,avx512dq,avx2,fma")))
#define VNNI_ROWS 8
#endif

/*
 * Rows are given as int8 x - 128 (A, lda bytes per row, a multiple of 4), columns as raw uint8 packed in
 * groups of 16 (B: group g, quad q holds the 16 columns' 4 bytes, so B + (g * nq + q) * 64).
 * (x - 128) . y = x . y - 128 sum(y), so with nb[c] = |y_c|^2 - 256 sum(y_c) the squared
 * distance is na[r] + nb[c] - 2 acc: exact in int32, written to G (m x k, row stride ldg) as
 * float32 (exact below 2^24; the caller makes sure every value is). nq = dim / 4 rounded up.
 * A must hold VNNI_ROWS - 1 readable rows past m and B whole pairs of groups (32 columns).
 * Returns 0, or -3 when the CPU lacks AVX-512 VNNI.
 */
#ifdef DQM_HAVE_AVX2_PATH
/* VNNI_ROWS (8) rows x 32 columns: 16 accumulators, named variables held in registers. With 12 rows (24
   accumulators, in an array) GCC 12 kept a copy of each on the stack, stored on every step of the loop:
   half the speed (a 1024 x 192 tile on Zen 4: 103 GMAC/s, 8 rows 207, 6 rows 209, 4 rows 195). */
#define VNNI_ZERO(r) __m512i acc##r##_0 = _mm512_setzero_si512(), acc##r##_1 = _mm512_setzero_si512();
#define VNNI_STEP(r)                                                                   \
    {                                                                                  \
        __m512i a = _mm512_set1_epi32(*(const int32_t *)(A + (r) * lda + 4 * q));      \
        acc##r##_0 = _mm512_dpbusd_epi32(acc##r##_0, b0, a);                           \
        acc##r##_1 = _mm512_dpbusd_epi32(acc##r##_1, b1, a);                           \
    }
#define VNNI_OUT(r)                                                                                       \
    if ((r) < rows) {                                                                                     \
        __m512i n = _mm512_set1_epi32(na[r]);                                                             \
        __m512i d0 = _mm512_sub_epi32(_mm512_add_epi32(n, nb0), _mm512_slli_epi32(acc##r##_0, 1));        \
        __m512i d1 = _mm512_sub_epi32(_mm512_add_epi32(n, nb1), _mm512_slli_epi32(acc##r##_1, 1));        \
        _mm512_mask_storeu_ps(G + (r) * ldg, m0, _mm512_cvtepi32_ps(d0));                                 \
        _mm512_mask_storeu_ps(G + (r) * ldg + 16, m1, _mm512_cvtepi32_ps(d1));                            \
    }
#define VNNI_ALL(X) X(0) X(1) X(2) X(3) X(4) X(5) X(6) X(7)

VNNI_TARGET
static void vnni8_block(const int8_t *A, int64_t lda, const uint8_t *Bg, int64_t nq, int64_t rows,
                        const int32_t *na, const int32_t *nb, float *G, int64_t ldg, __mmask16 m0, __mmask16 m1)
{
    VNNI_ALL(VNNI_ZERO)
    const uint8_t *B1 = Bg + nq * 64;
    for (int64_t q = 0; q < nq; ++q) {
        __m512i b0 = _mm512_loadu_si512((const void *)(Bg + q * 64));
        __m512i b1 = _mm512_loadu_si512((const void *)(B1 + q * 64));
        VNNI_ALL(VNNI_STEP)
    }
    __m512i nb0 = _mm512_maskz_loadu_epi32(m0, nb), nb1 = _mm512_maskz_loadu_epi32(m1, nb + 16);
    VNNI_ALL(VNNI_OUT)
}
#endif

/*
 * The operands of dqm_gemm_d2_u8 for the rows X[idx[i]] (i < n; idx NULL: the first n rows) of uint8
 * descriptors (dim bytes each, row stride ldx), packed in one pass without temporaries: rows as int8 x - 128
 * (width = 4 nq bytes each, padding 0), columns in groups of 16 features (4 bytes of each feature per step q,
 * 64 bytes a step; groups a multiple of 2, the features past n 0), na = |x|^2, nb = |x|^2 - 256 sum(x). The
 * caller zeroes what lies past n (the padding rows of A, the columns past n, na and nb past n).
 */
void dqm_pack_u8(const uint8_t *X, int64_t ldx, const int64_t *idx, int64_t n, int64_t dim, int64_t nq,
                 int8_t *rows, uint8_t *cols, int32_t *na, int32_t *nb)
{
    const int64_t width = 4 * nq;
    for (int64_t i = 0; i < n; ++i) {
        const uint8_t *x = X + (idx ? idx[i] : i) * ldx;
        int8_t *r = rows + i * width;
        uint8_t *c = cols + ((i / 16) * nq * 16 + i % 16) * 4;
        int32_t sq = 0, sum = 0;
        for (int64_t j = 0; j < width; ++j) {
            const uint8_t v = j < dim ? x[j] : 0;
            r[j] = j < dim ? (int8_t)(v ^ 0x80u) : 0;
            c[(j / 4) * 64 + j % 4] = v;
            sq += (int32_t)v * v;
            sum += v;
        }
        na[i] = sq;
        nb[i] = sq - 256 * sum;
    }
}

int32_t dqm_gemm_d2_u8(const int8_t *A, int64_t lda, const int32_t *na, int64_t m,
                       const uint8_t *B, const int32_t *nb, int64_t k, int64_t nq,
                       float *G, int64_t ldg)
{
#ifdef DQM_HAVE_AVX2_PATH
    resolve_simd();
    if (simd_level < 3)
        return -3;
    for (int64_t c = 0; c < k; c += 32) {
        int64_t left = k - c;
        __mmask16 m0 = left >= 16 ? 0xFFFF : (__mmask16)((1u << left) - 1u);
        __mmask16 m1 = left >= 32 ? 0xFFFF : (left > 16 ? (__mmask16)((1u << (left - 16)) - 1u) : 0);
        const uint8_t *Bg = B + (c / 16) * nq * 64;
        for (int64_t r = 0; r < m; r += VNNI_ROWS) {
            int64_t rows = m - r < VNNI_ROWS ? m - r : VNNI_ROWS;
            vnni8_block(A + r * lda, lda, Bg, nq, rows, na + r, nb + c, G + r * ldg + c, ldg, m0, m1);
        }
    }
    return 0;
#else
    return -3;
#endif
}

/*
 * One tile of the all-pairs pass for uint8 descriptors, GEMM and kernel fused: the squared
 * distances are made (dqm_gemm_d2_u8) in strips of PASS_STRIP rows into the caller's scratch
 * (PASS_STRIP x k floats, which stays in cache) and each strip goes through the tile kernel
 * at once, so the tile is never written out whole. diag != 0: rows and columns are the same
 * features (dqm_tile, the self pair skipped; wc/sc/rad2c/dens_c/err_c/cacc/cerr unused);
 * otherwise dqm_tile_sym. A, na: the tile's first row; B, nb: its first column (see
 * dqm_gemm_d2_u8). Candidate rows are tile rows. Returns the count, -1 past cap, -2 if
 * k > MAX_ROW, -3 without AVX-512 VNNI.
 */
#define PASS_STRIP 64

int64_t dqm_pass_tile_u8(const int8_t *A, int64_t lda, const int32_t *na, int64_t m,
                         const uint8_t *B, const int32_t *nb, int64_t k, int64_t nq, int32_t diag,
                         float *scratch, const float *wc, const float *sc, const float *wr, const float *sr,
                         int32_t kernel, const float *rad2r, const float *rad2c,
                         double *dens_r, double *err_r, double *dens_c, double *err_c,
                         float *cacc, float *cerr, int32_t *cand_r, int32_t *cand_c, int64_t cap)
{
    int64_t count = 0;
    if (k > MAX_ROW)
        return -2;
    for (int64_t r0 = 0; r0 < m; r0 += PASS_STRIP) {
        int64_t rows = m - r0 < PASS_STRIP ? m - r0 : PASS_STRIP;
        int32_t ok = dqm_gemm_d2_u8(A + r0 * lda, lda, na + r0, rows, B, nb, k, nq, scratch, k);
        if (ok < 0)
            return ok;
        int64_t got;
        if (diag)
            got = dqm_tile(scratch, rows, k, k, wc, sc, kernel, rad2r + r0, r0, dens_r + r0, err_r + r0,
                           cand_r + count, cand_c + count, cap - count);
        else
            got = dqm_tile_sym(scratch, rows, k, k, wc, sc, wr + r0, sr + r0, kernel, rad2r + r0, rad2c,
                               dens_r + r0, err_r + r0, dens_c, err_c, cacc, cerr,
                               cand_r + count, cand_c + count, cap - count);
        if (got < 0)
            return got;
        for (int64_t i = count; i < count + got; ++i)
            cand_r[i] += (int32_t)r0;
        count += got;
    }
    return count;
}

/*
 * Row and column minima of a tile of exact squared distances of uint8 descriptors (the sigma pass's tiles on
 * the integer kernel): made (dqm_gemm_d2_u8) in strips of PASS_STRIP rows into the caller's scratch
 * (PASS_STRIP x k floats, which stays in cache) and reduced at once, so the tile is never written out whole.
 * diag != 0: rows and columns are the same features, the self pairs (r, r) left out (FLT_MAX where a row or
 * column has no other entry). Operands as dqm_gemm_d2_u8 (A, na: the tile's first row; B, nb: its first
 * column). Returns 0, -2 if k > MAX_ROW, -3 without AVX-512 VNNI.
 */
int32_t dqm_min_tile_u8(const int8_t *A, int64_t lda, const int32_t *na, int64_t m,
                        const uint8_t *B, const int32_t *nb, int64_t k, int64_t nq, int32_t diag,
                        float *scratch, float *rmin, float *cmin)
{
    if (k > MAX_ROW)
        return -2;
    resolve_simd();
    for (int64_t c = 0; c < k; ++c)
        cmin[c] = FLT_MAX;
    for (int64_t r0 = 0; r0 < m; r0 += PASS_STRIP) {
        int64_t rows = m - r0 < PASS_STRIP ? m - r0 : PASS_STRIP;
        int32_t ok = dqm_gemm_d2_u8(A + r0 * lda, lda, na + r0, rows, B, nb, k, nq, scratch, k);
        if (ok < 0)
            return ok;
        for (int64_t r = 0; r < rows; ++r) {
            float *g = scratch + r * k;
            if (diag && r0 + r < k)
                g[r0 + r] = FLT_MAX;
            rmin[r0 + r] = minrow(g, k, cmin);
        }
    }
    return 0;
}

/*
 * Scan tile of the fast engine (dqm/core/inverted_lists.py). Columns are the
 * members of list `list`; rows are the features that scan it: its own n_own
 * members first (row r < n_own is column r + self_col), then features of
 * other lists (row_list[r] is a row's own list). A row of another list meets
 * a column in this tile and, when the column scans the row's list too
 * (bit row_list[r] of the column's col_bits, `words` 64-bit words per column),
 * again in the tile of the row's list: the pair is kept in the tile of the
 * larger list index only. Every kept pair of another list's row is used both
 * ways: the row's density gets the column's term (weights wc, sc) and the
 * column's density the row's (wr, sr); own rows take only their own direction
 * (their pairs appear in both orders). Edges: (r, c) with g < rad2r[r] (the
 * row as the child) and, for kept pairs of other lists' rows, (-1 - r, c) with
 * g < rad2c[c] (the column as the child). cacc is float scratch of length k.
 * Returns the count of edges written, -1 if more than cap, -2 if k > MAX_ROW.
 * No error bound: the fast engine's densities are approximate anyway.
 */
static inline int scan_keep(const uint64_t *col_bits, int64_t words, int64_t c, int32_t a)
{
    return !((col_bits[c * words + (a >> 6)] >> (a & 63)) & 1u);
}

/* Of the lanes `all` (bit l: column c + l, at most `lanes` of them), those a SIMD scan row keeps: all but the
   self pair on an own row; on a tested row those whose column does not scan the row's list. */
static inline unsigned scan_keep_lanes(unsigned all, int64_t c, int64_t lanes, int own, int64_t self, int test,
                                       const uint64_t *col_bits, int64_t words, int32_t a)
{
    unsigned keep = all;
    if (own) {
        if (self >= c && self < c + lanes)
            keep &= ~(1u << (unsigned)(self - c));
    } else if (test) {
        /* branchless: whether a column scans the row's list is as good as random */
        const uint64_t *p = col_bits + c * words + (a >> 6);
        const unsigned sh = (unsigned)(a & 63);
        unsigned scanned = 0;
        for (int64_t l = 0; l < lanes; ++l)
            scanned |= (unsigned)((p[l * words] >> sh) & 1u) << (unsigned)l;
        keep &= ~scanned;
    }
    return keep;
}

/* A SIMD scan row's edges of columns c + l, lane by lane: (r, c + l) where bit l of fwd is set (the row the
   child), then (-1 - r, c + l) where bit l of rev is (the column the child); the count goes on past cap. */
static inline int64_t scan_emit(unsigned fwd, unsigned rev, int32_t r, int64_t c, const float *g,
                                int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t count, int64_t cap)
{
    for (unsigned both = fwd | rev; both; both &= both - 1) {
        const int l = __builtin_ctz(both);
        if (fwd & (1u << l)) {
            if (count < cap) { cand_r[count] = r; cand_c[count] = (int32_t)(c + l); cand_g[count] = g[c + l]; }
            ++count;
        }
        if (rev & (1u << l)) {
            if (count < cap) { cand_r[count] = -1 - r; cand_c[count] = (int32_t)(c + l); cand_g[count] = g[c + l]; }
            ++count;
        }
    }
    return count;
}

static inline float term_scalar(int kernel, float g, float w, float s)
{
    float t = (g < 0.0f ? 0.0f : g) * w;
    if (kernel == KERNEL_GAUSSIAN)
        return exp_neg(t > 87.0f ? 87.0f : t) * s;
    return t < 1.0f ? (1.0f - t) * s : 0.0f;
}

static int64_t scan_row_scalar(int kernel, const float *g, int64_t k, const float *wc, const float *sc,
                               float wr, float sr, float limr, const float *rad2c, int own, int64_t self,
                               int test, const uint64_t *col_bits, int64_t words, int32_t a, int32_t r,
                               double *dens_r, float *cacc, int32_t *cand_r, int32_t *cand_c, float *cand_g,
                               int64_t count, int64_t cap, int64_t c_off)
{
    float acc = 0.0f;
    for (int64_t c = 0; c < k; ++c) {
        if (own) {
            if (c == self)
                continue;
        } else if (test && !scan_keep(col_bits, words, c, a)) {
            continue;
        }
        acc += term_scalar(kernel, g[c], wc[c], sc[c]);
        if (g[c] < limr) {
            if (count < cap) { cand_r[count] = r; cand_c[count] = (int32_t)(c + c_off); cand_g[count] = g[c]; }
            ++count;
        }
        if (!own) {
            cacc[c] += term_scalar(kernel, g[c], wr, sr);
            if (g[c] < rad2c[c]) {
                if (count < cap) { cand_r[count] = -1 - r; cand_c[count] = (int32_t)(c + c_off); cand_g[count] = g[c]; }
                ++count;
            }
        }
    }
    *dens_r += (double)acc;
    return count;
}

#ifdef DQM_HAVE_AVX2_PATH
__attribute__((target("avx2,fma")))
static inline __m256 terms8(int kernel, __m256 gv, __m256 wv, __m256 sv)
{
    __m256 t = _mm256_mul_ps(_mm256_max_ps(gv, _mm256_setzero_ps()), wv);
    if (kernel == KERNEL_GAUSSIAN)
        return _mm256_mul_ps(exp_neg8(_mm256_min_ps(t, _mm256_set1_ps(87.0f))), sv);
    return _mm256_mul_ps(_mm256_max_ps(_mm256_sub_ps(_mm256_set1_ps(1.0f), t), _mm256_setzero_ps()), sv);
}

__attribute__((target("avx2,fma")))
static int64_t scan_row_avx2(int kernel, const float *g, int64_t k, const float *wc, const float *sc,
                             float wr, float sr, float limr, const float *rad2c, int own, int64_t self,
                             int test, const uint64_t *col_bits, int64_t words, int32_t a, int32_t r,
                             double *dens_r, float *cacc, int32_t *cand_r, int32_t *cand_c, float *cand_g,
                             int64_t count, int64_t cap)
{
    __m256 acc = _mm256_setzero_ps();
    __m256 vlim = _mm256_set1_ps(limr), wrv = _mm256_set1_ps(wr), srv = _mm256_set1_ps(sr);
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        __m256 gv = _mm256_loadu_ps(g + c);
        const int keepbits = (int)scan_keep_lanes(0xffu, c, 8, own, self, test, col_bits, words, a);
        if (!keepbits)
            continue;
        __m256 keep = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
            _mm256_and_si256(_mm256_set1_epi32(keepbits), _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128)),
            _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128)));
        acc = _mm256_add_ps(acc, _mm256_and_ps(terms8(kernel, gv, _mm256_loadu_ps(wc + c), _mm256_loadu_ps(sc + c)), keep));
        int fwd = _mm256_movemask_ps(_mm256_cmp_ps(gv, vlim, _CMP_LT_OQ)) & keepbits;
        if (!own) {
            __m256 ca = _mm256_loadu_ps(cacc + c);
            _mm256_storeu_ps(cacc + c, _mm256_add_ps(ca, _mm256_and_ps(terms8(kernel, gv, wrv, srv), keep)));
        }
        int rev = own ? 0 : _mm256_movemask_ps(_mm256_cmp_ps(gv, _mm256_loadu_ps(rad2c + c), _CMP_LT_OQ)) & keepbits;
        count = scan_emit((unsigned)fwd, (unsigned)rev, r, c, g, cand_r, cand_c, cand_g, count, cap);
    }
    *dens_r += (double)hsum8(acc);
    return scan_row_scalar(kernel, g + c, k - c, wc + c, sc + c, wr, sr, limr, rad2c + c, own, self - c, test,
                           col_bits + c * words, words, a, r, dens_r, cacc + c, cand_r, cand_c, cand_g, count, cap, c);
}
#endif

#ifdef DQM_HAVE_AVX2_PATH
/* The scan row with AVX-512: 16 lanes, masks instead of a scalar tail; the terms are terms8's lane for
   lane (exp_neg16 is exp_neg8's), only the order of the float32 sums differs. */
AVX512_TARGET
static inline __m512 scan_terms16(int kernel, __m512 gv, __m512 wv, __m512 sv)
{
    __m512 t = _mm512_mul_ps(_mm512_max_ps(gv, _mm512_setzero_ps()), wv);
    if (kernel == KERNEL_GAUSSIAN)
        return _mm512_mul_ps(exp_neg16(_mm512_min_ps(t, _mm512_set1_ps(87.0f))), sv);
    return _mm512_mul_ps(_mm512_max_ps(_mm512_sub_ps(_mm512_set1_ps(1.0f), t), _mm512_setzero_ps()), sv);
}

AVX512_TARGET
static int64_t scan_row_avx512(int kernel, const float *g, int64_t k, const float *wc, const float *sc,
                               float wr, float sr, float limr, const float *rad2c, int own, int64_t self,
                               int test, const uint64_t *col_bits, int64_t words, int32_t a, int32_t r,
                               double *dens_r, float *cacc, int32_t *cand_r, int32_t *cand_c, float *cand_g,
                               int64_t count, int64_t cap)
{
    __m512 acc = _mm512_setzero_ps();
    __m512 vlim = _mm512_set1_ps(limr), wrv = _mm512_set1_ps(wr), srv = _mm512_set1_ps(sr);
    for (int64_t c = 0; c < k; c += 16) {
        const __mmask16 m = tail_mask(k - c);
        const __mmask16 keep = (__mmask16)scan_keep_lanes(m, c, k - c < 16 ? k - c : 16, own, self, test, col_bits,
                                                          words, a);
        if (!keep)
            continue;
        __m512 gv = _mm512_maskz_loadu_ps(m, g + c);
        acc = _mm512_mask_add_ps(acc, keep, acc, scan_terms16(kernel, gv, _mm512_maskz_loadu_ps(m, wc + c),
                                                              _mm512_maskz_loadu_ps(m, sc + c)));
        unsigned fwd = _mm512_mask_cmp_ps_mask(keep, gv, vlim, _CMP_LT_OQ), rev = 0;
        if (!own) {
            __m512 ca = _mm512_maskz_loadu_ps(m, cacc + c);
            _mm512_mask_storeu_ps(cacc + c, m, _mm512_mask_add_ps(ca, keep, ca, scan_terms16(kernel, gv, wrv, srv)));
            rev = _mm512_mask_cmp_ps_mask(keep, gv, _mm512_maskz_loadu_ps(m, rad2c + c), _CMP_LT_OQ);
        }
        count = scan_emit(fwd, rev, r, c, g, cand_r, cand_c, cand_g, count, cap);
    }
    *dens_r += (double)_mm512_reduce_add_ps(acc);
    return count;
}
#endif

int64_t dqm_scan_tile(const float *G, int64_t m, int64_t k, int64_t ldg,
                      const float *wc, const float *sc, const float *wr, const float *sr, int32_t kernel,
                      const float *rad2r, const float *rad2c, int64_t n_own, int64_t self_col,
                      const int32_t *row_list, const uint64_t *col_bits, int64_t words, int32_t list,
                      double *dens_r, double *dens_c, float *cacc,
                      int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t cap)
{
    int64_t count = 0;
    if (k > MAX_ROW)
        return -2;
    resolve_simd();
    for (int64_t c = 0; c < k; ++c)
        cacc[c] = 0.0f;
    for (int64_t r = 0; r < m; ++r) {
        int own = r < n_own;
        int32_t a = row_list[r];
        int test = !own && a > list; /* both ways scanned: kept in the larger list's tile */
        const float *g = G + r * ldg;
#ifdef DQM_HAVE_AVX2_PATH
        if (simd_level >= 2)
            count = scan_row_avx512(kernel, g, k, wc, sc, wr[r], sr[r], rad2r[r], rad2c, own, r + self_col, test,
                                    col_bits, words, a, (int32_t)r, dens_r + r, cacc, cand_r, cand_c, cand_g, count,
                                    cap);
        else if (simd_level >= 1)
            count = scan_row_avx2(kernel, g, k, wc, sc, wr[r], sr[r], rad2r[r], rad2c, own, r + self_col, test,
                                  col_bits, words, a, (int32_t)r, dens_r + r, cacc, cand_r, cand_c, cand_g, count, cap);
        else
#endif
            count = scan_row_scalar(kernel, g, k, wc, sc, wr[r], sr[r], rad2r[r], rad2c, own, r + self_col, test,
                                    col_bits, words, a, (int32_t)r, dens_r + r, cacc, cand_r, cand_c, cand_g, count, cap, 0);
        if ((r + 1) % SUM_CHAIN == 0 || r + 1 == m) {
            for (int64_t c = 0; c < k; ++c) {
                dens_c[c] += (double)cacc[c];
                cacc[c] = 0.0f;
            }
        }
    }
    return count > cap ? -1 : count;
}

/*
 * One task of the fast engine's scan on uint8 descriptors, in one call (the Python loop it replaces paid
 * about as much in per-call overhead as the kernels' own time): the task's m rows (indices idx into the
 * operands, which are in list order) are gathered into the thread's buffers A / na (m + VNNI_ROWS rows),
 * with their weights, activity, search radius min(rad2, limit) and list; then for every block of at
 * most MAX_ROW of the list's columns lo..hi, strip by strip of SUM_CHAIN rows, their exact squared distances
 * (dqm_gemm_d2_u8 from the multiple of 32 below the block, into G: SUM_CHAIN x (MAX_ROW + 32) floats, which
 * stay in cache) go through dqm_scan_tile. The same operations in the same order
 * as U8Operands.d2 and scan_tile on the gathered rows one block at a time, so the same bits (a test checks). dens_r (m) and dens_c
 * (hi - lo) are added to; edges as dqm_scan_tile's, their columns the features' indices (c0 added). limit is read once
 * per row and column (another thread may tighten it meanwhile: any value read is a valid radius).
 * row_f: 3 m floats of scratch; row_list: m; rad2c, cacc: MAX_ROW. Returns the count of edges, -1 past
 * cap, -2 / -3 as the kernels.
 */
int64_t dqm_scan_task(const int8_t *rows_op, int64_t lda, const int32_t *na_op, const uint8_t *cols_op,
                      const int32_t *nb_op, int64_t nq, const int64_t *idx, int64_t m, int64_t lo, int64_t hi,
                      int64_t n_own, int64_t r0, const float *w, const float *s, int32_t kernel,
                      const float *rad2, const volatile float *limit, const int32_t *lists, const uint64_t *bits,
                      int64_t words, int32_t list, int8_t *A, int32_t *na, float *G, float *row_f,
                      int32_t *row_list, float *rad2c, float *cacc, double *dens_r, double *dens_c,
                      int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t cap)
{
    float *wr = row_f, *sr = row_f + m, *rad2r = row_f + 2 * m;
    int64_t count = 0;
    for (int64_t r = 0; r < m; ++r) {
        int64_t i = idx[r];
        memcpy(A + r * lda, rows_op + i * lda, (size_t)lda);
        na[r] = na_op[i];
        wr[r] = w[i];
        sr[r] = s[i];
        float lim = limit[i];
        rad2r[r] = rad2[i] < lim ? rad2[i] : lim;
        row_list[r] = lists[i];
    }
    for (int64_t c0 = lo; c0 < hi; c0 += MAX_ROW) {
        int64_t c1 = hi - c0 < MAX_ROW ? hi : c0 + MAX_ROW;
        int64_t b = c0 - c0 % 32, k = c1 - b;
        for (int64_t c = c0; c < c1; ++c) {
            float lim = limit[c];
            rad2c[c - c0] = rad2[c] < lim ? rad2[c] : lim;
        }
        /* strips of SUM_CHAIN rows: a strip's distances stay in cache, and dqm_scan_tile's column sums are
           carried over at every SUM_CHAIN rows as over the whole block, so the same bits */
        for (int64_t s0 = 0; s0 < m; s0 += SUM_CHAIN) {
            int64_t rows = m - s0 < SUM_CHAIN ? m - s0 : SUM_CHAIN;
            int32_t code = dqm_gemm_d2_u8(A + s0 * lda, lda, na + s0, rows, cols_op + (b / 16) * nq * 64, nb_op + b,
                                          k, nq, G, k);
            if (code < 0)
                return code;
            int64_t own = n_own - s0 < 0 ? 0 : n_own - s0;
            int64_t got = dqm_scan_tile(G + (c0 - b), rows, c1 - c0, k, w + c0, s + c0, wr + s0, sr + s0, kernel,
                                        rad2r + s0, rad2c, own, lo + r0 + s0 - c0, row_list + s0,
                                        bits + c0 * words, words, list, dens_r + s0, dens_c + (c0 - lo), cacc,
                                        cand_r + count, cand_c + count, cand_g + count, cap - count);
            if (got < 0)
                return got;
            for (int64_t e = count; e < count + got; ++e) {
                cand_r[e] += cand_r[e] >= 0 ? (int32_t)s0 : -(int32_t)s0;
                cand_c[e] += (int32_t)c0;
            }
            count += got;
        }
    }
    return count;
}

/*
 * The fast engine's candidate keeper: each child's k nearest candidates, ordered by (g, cand).
 *
 * Edges come as the scan tile writes them: (r, c) with row r the child (child = rows[r], cand = c) or
 * (-1 - r, c) with column c the child (child = c, cand = rows[-1 - r]); with image (may be NULL) pairs
 * within one image are skipped. best_g / best_c hold k slots per child (child * k ...), count how many
 * are filled, and lim[child] is set, once the k slots are full, to the smallest float above the k-th g:
 * an edge with g >= lim cannot enter (the scan tile takes lim as a radius: it tests g < lim). The kept
 * set is each child's k smallest (g, cand) of all edges offered, whatever their order: deterministic.
 * Returns the number of edges that entered.
 */
int64_t dqm_keep_nearest(const int32_t *er, const int32_t *ec, const float *eg, int64_t m,
                         const int64_t *rows, const int32_t *image, int32_t k,
                         float *best_g, int32_t *best_c, int32_t *count, float *lim)
{
    int64_t entered = 0;
    for (int64_t e = 0; e < m; ++e) {
        int64_t child, cand;
        if (er[e] >= 0) {
            child = rows[er[e]];
            cand = ec[e];
        } else {
            child = ec[e];
            cand = rows[-1 - (int64_t)er[e]];
        }
        if (image && image[child] == image[cand])
            continue;
        float g = eg[e];
        float *bg = best_g + child * (int64_t)k;
        int32_t *bc = best_c + child * (int64_t)k;
        int32_t n = count[child];
        if (n == k && (g > bg[k - 1] || (g == bg[k - 1] && cand >= bc[k - 1])))
            continue;
        int32_t at = n < k ? n : k - 1; /* the slot freed: the end, or the k-th when full */
        while (at > 0 && (bg[at - 1] > g || (bg[at - 1] == g && bc[at - 1] > cand))) {
            bg[at] = bg[at - 1];
            bc[at] = bc[at - 1];
            --at;
        }
        bg[at] = g;
        bc[at] = (int32_t)cand;
        if (n < k)
            count[child] = ++n;
        if (n == k)
            lim[child] = nextafterf(bg[k - 1], INFINITY);
        ++entered;
    }
    return entered;
}

/*
 * QuickMatch's break/merge (dqm/core/tree.py, merge_clusters): the m tree edges child[e] -> parent[e] at
 * distance d[e], already in increasing (d, child) order, joined by union-find. Clusters of child and parent
 * merge iff d < rho * min(scale_child, scale_parent) (a cluster's scale: the least sigma of its members, in
 * double as the Python loop computes it) and their image sets are disjoint. A cluster's images are held
 * sorted (the smaller set is looked up in the larger and merged into a new array). Writes every feature's
 * root to root (n entries). Returns 0, or -4 when memory runs out.
 */
static int64_t find_root(int64_t *root, int64_t i)
{
    int64_t r = i;
    while (root[r] != r)
        r = root[r];
    while (root[i] != r) {
        int64_t next = root[i];
        root[i] = r;
        i = next;
    }
    return r;
}

static int has_image(const int64_t *set, int64_t len, int64_t img)
{
    int64_t lo = 0, hi = len;
    while (lo < hi) {
        int64_t mid = lo + (hi - lo) / 2;
        if (set[mid] < img)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo < len && set[lo] == img;
}

int64_t dqm_merge_clusters(int64_t n, int64_t m, const int64_t *child, const int64_t *parent, const double *d,
                           const double *sigma, const int64_t *image, double rho, int64_t *root)
{
    double *scale = (double *)malloc(sizeof(double) * (size_t)(n > 0 ? n : 1));
    int64_t **sets = (int64_t **)calloc((size_t)(n > 0 ? n : 1), sizeof(int64_t *)); /* NULL: {image[i]} */
    int64_t *len = (int64_t *)malloc(sizeof(int64_t) * (size_t)(n > 0 ? n : 1));
    int64_t code = 0;
    if (!scale || !sets || !len) {
        code = -4;
        goto done;
    }
    for (int64_t i = 0; i < n; ++i) {
        root[i] = i;
        scale[i] = sigma[i];
        len[i] = 1;
    }
    for (int64_t e = 0; e < m; ++e) {
        int64_t rj = find_root(root, child[e]), rp = find_root(root, parent[e]);
        if (rj == rp)
            continue;
        double lim = rho * (scale[rp] < scale[rj] ? scale[rp] : scale[rj]); /* Python's min(): NaN as it does */
        if (!(d[e] < lim))
            continue;
        if (len[rj] > len[rp]) { /* look the smaller set up in the larger */
            int64_t t = rj;
            rj = rp;
            rp = t;
        }
        const int64_t *sj = sets[rj] ? sets[rj] : &image[rj];
        const int64_t *sp = sets[rp] ? sets[rp] : &image[rp];
        int clash = 0;
        for (int64_t a = 0; a < len[rj] && !clash; ++a)
            clash = has_image(sp, len[rp], sj[a]);
        if (clash)
            continue;
        int64_t total = len[rj] + len[rp];
        int64_t *merged = (int64_t *)malloc(sizeof(int64_t) * (size_t)total);
        if (!merged) {
            code = -4;
            goto done;
        }
        int64_t a = 0, b = 0, k = 0;
        while (a < len[rj] && b < len[rp])
            merged[k++] = sj[a] < sp[b] ? sj[a++] : sp[b++];
        while (a < len[rj])
            merged[k++] = sj[a++];
        while (b < len[rp])
            merged[k++] = sp[b++];
        free(sets[rj]);
        free(sets[rp]);
        sets[rj] = NULL;
        sets[rp] = merged;
        len[rp] = total;
        root[rj] = rp;
        scale[rp] = scale[rj] < scale[rp] ? scale[rj] : scale[rp];
    }
    for (int64_t i = 0; i < n; ++i)
        root[i] = find_root(root, i);
done:
    if (sets)
        for (int64_t i = 0; i < n; ++i)
            free(sets[i]);
    free(sets);
    free(scale);
    free(len);
    return code;
}

/* Exact squared distance of two uint8 rows (integer sums: every path gives the same value). */
static inline int32_t sq_dist_u8_scalar(const uint8_t *x, const uint8_t *y, int64_t dim)
{
    int32_t acc = 0;
    for (int64_t j = 0; j < dim; ++j) {
        int32_t t = (int32_t)x[j] - (int32_t)y[j];
        acc += t * t;
    }
    return acc;
}

#ifdef DQM_HAVE_AVX2_PATH
/* The same with AVX2: 16 bytes widened to int16, differences squared and summed in pairs (madd). */
__attribute__((target("avx2,fma")))
static int32_t sq_dist_u8_avx2(const uint8_t *x, const uint8_t *y, int64_t dim)
{
    __m256i acc = _mm256_setzero_si256();
    int64_t j = 0;
    for (; j + 16 <= dim; j += 16) {
        __m256i a = _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(x + j)));
        __m256i b = _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(y + j)));
        __m256i d = _mm256_sub_epi16(a, b);
        acc = _mm256_add_epi32(acc, _mm256_madd_epi16(d, d));
    }
    __m128i h = _mm_add_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0x4E));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0xB1));
    return _mm_cvtsi128_si32(h) + sq_dist_u8_scalar(x + j, y + j, dim - j);
}
#endif

/*
 * Exact squared distances of uint8 rows: out[e] = |X[a[e]] - X[b[e]]|^2 (int32 sums: dim <= 32768).
 */
void dqm_sq_dist_u8(const uint8_t *X, int64_t dim, const int64_t *a, const int64_t *b, int64_t m, double *out)
{
    for (int64_t e = 0; e < m; ++e)
        out[e] = (double)sq_dist_u8_scalar(X + a[e] * dim, X + b[e] * dim, dim);
}

/* v (column j) into the sorted run val / o of n <= t entries, after its equals; a full run drops its last. */
static inline void smallest_insert(float *val, int32_t *o, int32_t *n, int32_t t, float v, int32_t j)
{
    if (*n == t)
        *n = t - 1; /* the run's last leaves */
    int32_t p = *n;
    while (p > 0 && val[p - 1] > v) {
        val[p] = val[p - 1];
        o[p] = o[p - 1];
        --p;
    }
    val[p] = v;
    o[p] = j;
    ++*n;
}

/* Column j of value v (not NaN) as a key in (value, index) order: the float's bits made unsigned in its order
   (-0 as +0, which compares equal to it) above the index. */
static inline uint64_t column_key(float v, int64_t j)
{
    v += 0.0f;
    uint32_t u;
    memcpy(&u, &v, sizeof u);
    return (uint64_t)((u & 0x80000000u) ? ~u : (u | 0x80000000u)) << 32 | (uint64_t)j;
}

#ifdef DQM_HAVE_AVX2_PATH
/* Once the run is full, 8 columns at a time are compared with its last value and only those strictly
   smaller go through the scalar insertion, in column order: the same result (NaN compares false, as
   +inf does against a full run). */
__attribute__((target("avx2")))
static int64_t smallest_avx2(const float *d, int64_t j, int64_t k, float *val, int32_t *o, int32_t *n, int32_t t)
{
    for (; j + 8 <= k; j += 8) {
        unsigned below = (unsigned)_mm256_movemask_ps(
            _mm256_cmp_ps(_mm256_loadu_ps(d + j), _mm256_set1_ps(val[t - 1]), _CMP_LT_OQ));
        for (; below; below &= below - 1) {
            const int l = __builtin_ctz(below);
            if (d[j + l] < val[t - 1]) /* the threshold fell since the compare */
                smallest_insert(val, o, n, t, d[j + l], (int32_t)(j + l));
        }
    }
    return j;
}

/* The largest of the t chunk minima of one row (chunks of w = k / t columns, w a multiple of 8), NaN as
   +inf: min(x, acc) keeps acc when x is NaN. */
__attribute__((target("avx2")))
static float smallest_tau_avx2(const float *d, int64_t w, int32_t t)
{
    float tau = -INFINITY;
    for (int32_t c = 0; c < t; ++c) {
        __m256 acc = _mm256_set1_ps(INFINITY);
        for (int64_t i = c * w; i < (c + 1) * w; i += 8)
            acc = _mm256_min_ps(_mm256_loadu_ps(d + i), acc);
        __m128 h = _mm_min_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps(acc, 1));
        h = _mm_min_ps(h, _mm_movehl_ps(h, h));
        h = _mm_min_ss(h, _mm_shuffle_ps(h, h, 1));
        float lo = _mm_cvtss_f32(h);
        tau = lo > tau ? lo : tau;
    }
    return tau;
}

/* keys_at_most's vector part: blocks of 8 columns; returns the first column left for the scalar loop. */
__attribute__((target("avx2")))
static int64_t keys_at_most_avx2(const float *d, int64_t k, float tau, uint64_t *key, int64_t *cnt)
{
    const __m256 t8 = _mm256_set1_ps(tau);
    int64_t j = 0, n = *cnt;
    for (; j + 8 <= k; j += 8) {
        unsigned in = (unsigned)_mm256_movemask_ps(_mm256_cmp_ps(_mm256_loadu_ps(d + j), t8, _CMP_LE_OQ));
        for (; in; in &= in - 1) {
            const int l = __builtin_ctz(in);
            key[n++] = column_key(d[j + l], j + l);
        }
    }
    *cnt = n;
    return j;
}
#endif

/* key[0..t) := the t smallest of the cnt distinct keys, ascending (quickselect, then insertion). */
static void smallest_keys(uint64_t *key, int64_t cnt, int32_t t)
{
    int64_t lo = 0, hi = cnt - 1;
    const int64_t want = t - 1;
    while (lo < hi) {
        uint64_t a = key[lo], b = key[lo + (hi - lo) / 2], c = key[hi];
        uint64_t pivot = a < b ? (b < c ? b : (a < c ? c : a)) : (a < c ? a : (b < c ? c : b));
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (key[i] < pivot)
                ++i;
            while (key[j] > pivot)
                --j;
            if (i <= j) {
                uint64_t x = key[i];
                key[i++] = key[j];
                key[j--] = x;
            }
        }
        if (want <= j)
            hi = j;
        else if (want >= i)
            lo = i;
        else
            break;
    }
    for (int32_t p = 1; p < t; ++p) {
        uint64_t x = key[p];
        int32_t q = p;
        for (; q > 0 && key[q - 1] > x; --q)
            key[q] = key[q - 1];
        key[q] = x;
    }
}

/* The columns of row d at or below tau (finite) as keys (value, index), in *cnt; AVX2 compares 8 at a time. */
static int64_t keys_at_most(const float *d, int64_t k, float tau, uint64_t *key)
{
    int64_t cnt = 0, j = 0;
#ifdef DQM_HAVE_AVX2_PATH
    if (simd_level >= 1)
        j = keys_at_most_avx2(d, k, tau, key, &cnt);
#endif
    for (; j < k; ++j)
        if (d[j] <= tau) /* NaN: never */
            key[cnt++] = column_key(d[j], j);
    return cnt;
}

/*
 * The t smallest entries of every row of D (m x k floats, row stride ldd) as column indices ordered by
 * (value, index), into out (m x t); t <= k. NaN counts as +inf. The fast engine's nearest lists. The
 * largest of t chunk minima, tau, bounds the t-th smallest from above (the t minima are t entries); the
 * entries at or below it (about 110 of 512 for t = 32 on the 150k generated features' distances to their
 * centroids) become keys (value, index) whose t smallest a quickselect finds and an insertion sort orders:
 * 0.27 s for 150k x 512, t = 32, where a sorted run of the t best so far, which a later column enters when
 * strictly smaller than its last, took 0.36 s (a max-heap more, a partition and a sort of every row in
 * numpy about twice). The run remains where tau is not finite (a chunk all NaN or +inf) or keys cannot be
 * made.
 */
void dqm_smallest(const float *D, int64_t m, int64_t k, int64_t ldd, int32_t t, int32_t *out)
{
    if (t <= 0 || t > k)
        return;
    float *val = (float *)malloc(sizeof(float) * (size_t)t);
    if (val == NULL)
        return;
    uint64_t *key = (uint64_t *)malloc(sizeof(uint64_t) * (size_t)k);
    resolve_simd();
    for (int64_t r = 0; r < m; ++r) {
        const float *d = D + r * ldd;
        int32_t *o = out + r * t;
        int32_t n = 0;
        int64_t j = 0;
        /* the t chunks' minima are t entries: the t-th smallest is at most their largest, tau; entries
           above it cannot be among the t, so the run fills only with those at or below it (in column
           order, so the same run) */
        float tau = -INFINITY;
#ifdef DQM_HAVE_AVX2_PATH
        if (simd_level >= 1 && k % t == 0 && (k / t) % 8 == 0)
            tau = smallest_tau_avx2(d, k / t, t);
        else
#endif
        for (int32_t c = 0; c < t; ++c) {
            float lo = INFINITY;
            for (int64_t i = c * k / t; i < (c + 1) * k / t; ++i)
                lo = d[i] < lo ? d[i] : lo; /* NaN: never smaller, as +inf */
            tau = lo > tau ? lo : tau;
        }
        if (key != NULL && tau < INFINITY) {
            int64_t cnt = keys_at_most(d, k, tau, key);
            if (cnt >= t) { /* always, tau being finite: each of the t chunks holds an entry at or below it */
                smallest_keys(key, cnt, t);
                for (int32_t i = 0; i < t; ++i)
                    o[i] = (int32_t)(key[i] & 0xFFFFFFFFu);
                continue;
            }
        }
        for (; j < k && n < t; ++j) {
            float v = d[j] != d[j] ? INFINITY : d[j];
            if (v <= tau)
                smallest_insert(val, o, &n, t, v, (int32_t)j);
        }
#ifdef DQM_HAVE_AVX2_PATH
        if (simd_level >= 1)
            j = smallest_avx2(d, j, k, val, o, &n, t);
#endif
        for (; j < k; ++j) {
            float v = d[j];
            if (v < val[t - 1]) /* NaN: never */
                smallest_insert(val, o, &n, t, v, (int32_t)j);
        }
    }
    free(key);
    free(val);
}

/*
 * Every child's nearest candidate (tree.nearest_candidates / select_parents): for the m edges
 * child[e] -> cand[e] at dist[e], the first edge of each child in (dist, key, position) order, key[e]
 * (or cand[e] when key is NULL); with density given, only candidates that rank above their child count
 * (higher density, then the lower index). One pass, memory O(n): parent / pdist / row (n entries, filled
 * by the caller with -1 / inf / -1) are updated on a strictly better edge only, so among equal (dist, key)
 * the first position stays. A NaN distance comes after every number, as in a sort.
 */
void dqm_nearest_above(int64_t m, const int64_t *child, const int64_t *cand, const double *dist,
                       const int64_t *key, const double *density, int64_t *parent, double *pdist, int64_t *row)
{
    for (int64_t e = 0; e < m; ++e) {
        const int64_t c = child[e], p = cand[e];
        if (density && !(density[p] > density[c] || (density[p] == density[c] && p < c)))
            continue;
        const double d = dist[e];
        const int64_t k = key ? key[e] : p;
        const int64_t r = row[c];
        int better;
        if (r < 0)
            better = 1;
        else if (d != d)
            better = 0;
        else if (pdist[c] != pdist[c] || d < pdist[c])
            better = 1;
        else
            better = d == pdist[c] && k < (key ? key[r] : parent[c]); /* the held edge's key */
        if (better) {
            parent[c] = p;
            pdist[c] = d;
            row[c] = e;
        }
    }
}

/* ---- guided matching: the candidates near epipolar lines and each side's two nearest ---- */

/* One candidate (r, c) at distance d into the best / second-best of row r (ties: the lower column). */
static inline void best_two_update(int64_t *best, double *bd, double *sd, int64_t k, int64_t other, double d)
{
    if (d < bd[k] || (d == bd[k] && other < best[k])) {
        if (bd[k] < sd[k])
            sd[k] = bd[k]; /* the old best becomes a second */
        bd[k] = d;
        best[k] = other;
    } else if (d < sd[k]) {
        sd[k] = d;
    }
}

/* From p on, the first index below hi with key >= v (right = 0) or key > v (right = 1): the bound of a
 * value no smaller than the one p was found for, so the sweep only moves forward. */
static inline int64_t sweep_bound(const double *key, int64_t p, int64_t hi, double v, int right)
{
    if (right)
        while (p < hi && key[p] <= v)
            ++p;
    else
        while (p < hi && key[p] < v)
            ++p;
    return p;
}

/*
 * One of the two searches of dqm/vision/guided.py's epipolar candidates, fused with the descriptor
 * distances and each side's two nearest (the numpy version: consistent_pairs + _best_two there).
 *
 * The points of the searched image are in groups (rings of distance from the epipole, or one group
 * when the lines are parallel); within a group, sorted by key (angle about the epipole in [0, period),
 * or the offset along the lines' common normal when period == 0). Line k's candidates in group g are
 * the points whose key lies within [center[k] - w[g], center[k] + w[g]] (modulo period; w[g] < 0:
 * every point of the group). A candidate (line k, point p) is the pair (r, c) = (k, p) when
 * rows_are_lines, else (p, k). With e = L[r] . (xb[c], 1) (L: image a's features' lines in image b),
 * it is kept when |e| <= tol sqrt(nb[r]) is true (rows_are_lines) or false (the other search: the
 * first one took those), and e^2 <= t2 (nb[r] + na[c]) (Sampson). A kept pair's distance is the exact
 * Euclidean distance of the uint8 descriptors X_line[k] (line k's feature) and X_sorted[q] (the point at
 * sorted position q: copies in that order keep a window's descriptors together in memory); it updates row r's and column c's best
 * (lowest distance, ties to the lower index on the other side) and second-lowest distance.
 * Returns the number of pairs kept.
 */
int64_t dqm_epipolar_scan(int64_t n_lines, const double *center, const int64_t *by_center, int64_t n_groups,
                          const int64_t *group_start, const double *group_w, const double *key, const int64_t *point,
                          double period, int32_t rows_are_lines, const double *L, const double *nb,
                          const double *na, const double *xb, double tol, double t2, const uint8_t *X_line,
                          const uint8_t *X_sorted, int64_t dim, int64_t *best_r, double *bd_r, double *sd_r,
                          int64_t *best_c, double *bd_c, double *sd_c)
{
    int64_t kept = 0;
    resolve_simd();
    int simd = simd_level >= 1;
    (void)simd;
    for (int64_t g = 0; g < n_groups; ++g) {
        int64_t gs = group_start[g], ge = group_start[g + 1];
        if (gs == ge)
            continue;
        double w = group_w[g];
        int whole = w < 0 || (period > 0 && 2 * w >= period);
        /* the lines in order of center: every bound below only moves forward */
        int64_t p_lo = gs, p_hi = gs, p_wlo = gs, p_whi = gs;
        for (int64_t o = 0; o < n_lines; ++o) {
            int64_t k = by_center[o];
            int64_t span[4]; /* up to two ranges of sorted positions */
            int n_span = 0;
            if (whole) {
                span[0] = gs;
                span[1] = ge;
                n_span = 1;
            } else {
                double lo = center[k] - w, hi = center[k] + w;
                if (period > 0 && lo < 0) { /* wraps below 0: [lo + period, period) too */
                    p_wlo = sweep_bound(key, p_wlo, ge, lo + period, 0);
                    span[0] = p_wlo;
                    span[1] = ge;
                    n_span = 1;
                    lo = 0;
                } else if (period > 0 && hi >= period) { /* wraps past period: [0, hi - period] too */
                    p_whi = sweep_bound(key, p_whi, ge, hi - period, 1);
                    span[0] = gs;
                    span[1] = p_whi;
                    n_span = 1;
                    hi = period;
                }
                p_lo = sweep_bound(key, p_lo, ge, lo, 0);
                if (p_hi < p_lo)
                    p_hi = p_lo;
                p_hi = sweep_bound(key, p_hi, ge, hi, 1);
                span[2 * n_span] = p_lo;
                span[2 * n_span + 1] = p_hi;
                ++n_span;
            }
            for (int s = 0; s < n_span; ++s) {
                for (int64_t q = span[2 * s]; q < span[2 * s + 1]; ++q) {
                    int64_t p = point[q];
                    int64_t r = rows_are_lines ? k : p, c = rows_are_lines ? p : k;
                    const double *l = L + 3 * r;
                    double e = l[0] * xb[2 * c] + l[1] * xb[2 * c + 1] + l[2];
                    int near = fabs(e) <= tol * sqrt(nb[r]);
                    if (near != (rows_are_lines != 0))
                        continue;
                    if (!(e * e <= t2 * (nb[r] + na[c])))
                        continue;
                    const uint8_t *x = X_line + k * dim, *y = X_sorted + q * dim;
#ifdef DQM_HAVE_AVX2_PATH
                    int32_t acc = simd ? sq_dist_u8_avx2(x, y, dim) : sq_dist_u8_scalar(x, y, dim);
#else
                    int32_t acc = sq_dist_u8_scalar(x, y, dim);
#endif
                    double d = sqrt((double)acc);
                    best_two_update(best_r, bd_r, sd_r, r, c, d);
                    best_two_update(best_c, bd_c, sd_c, c, r, d);
                    ++kept;
                }
            }
        }
    }
    return kept;
}
