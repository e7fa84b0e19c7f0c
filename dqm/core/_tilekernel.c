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
 * CPUs with AVX2+FMA (checked at run time) the row loops use AVX2 intrinsics;
 * elsewhere the portable scalar loops run.
 */
#include <stdint.h>
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
   columns with g < lim. */
typedef struct { float acc, err; int64_t hits; } RowOut;

static RowOut row_scalar(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim)
{
    RowOut o = {0.0f, 0.0f, 0};
    for (int64_t c = 0; c < k; ++c) {
        float d2 = g[c] < 0.0f ? 0.0f : g[c];
        float t = d2 * w[c];
        if (kernel == KERNEL_GAUSSIAN) {
            if (t > 87.0f) t = 87.0f;
            float e = exp_neg(t) * s[c];
            o.acc += e;
            o.err += e * w[c];
        } else {
            float q = 1.0f - t;
            if (q > 0.0f) o.acc += q * s[c];
            if (q > -0.01f) o.err += w[c] * s[c];
        }
        o.hits += g[c] < lim;
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
static RowOut row_avx2(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim)
{
    __m256 acc = _mm256_setzero_ps(), err = _mm256_setzero_ps();
    __m256 zero = _mm256_setzero_ps(), vmax = _mm256_set1_ps(87.0f), one = _mm256_set1_ps(1.0f);
    __m256 edge = _mm256_set1_ps(-0.01f), vlim = _mm256_set1_ps(lim);
    int64_t hits = 0;
    int64_t c = 0;
    for (; c + 8 <= k; c += 8) {
        __m256 gv = _mm256_loadu_ps(g + c);
        __m256 wv = _mm256_loadu_ps(w + c);
        __m256 sv = _mm256_loadu_ps(s + c);
        __m256 t = _mm256_mul_ps(_mm256_max_ps(gv, zero), wv);
        if (kernel == KERNEL_GAUSSIAN) {
            __m256 e = _mm256_mul_ps(exp_neg8(_mm256_min_ps(t, vmax)), sv);
            acc = _mm256_add_ps(acc, e);
            err = _mm256_fmadd_ps(e, wv, err);
        } else {
            __m256 q = _mm256_sub_ps(one, t);
            acc = _mm256_add_ps(acc, _mm256_mul_ps(_mm256_max_ps(q, zero), sv));
            __m256 near = _mm256_and_ps(_mm256_cmp_ps(q, edge, _CMP_GT_OQ), _mm256_mul_ps(wv, sv));
            err = _mm256_add_ps(err, near);
        }
        hits += __builtin_popcount(_mm256_movemask_ps(_mm256_cmp_ps(gv, vlim, _CMP_LT_OQ)));
    }
    RowOut tail = row_scalar(kernel, g + c, w + c, s + c, k - c, lim);
    RowOut o;
    o.acc = hsum8(acc) + tail.acc;
    o.err = hsum8(err) + tail.err;
    o.hits = hits + tail.hits;
    return o;
}
#endif

static int use_avx2 = -1;

static RowOut row_terms(int kernel, const float *g, const float *w, const float *s, int64_t k, float lim)
{
#ifdef DQM_HAVE_AVX2_PATH
    if (use_avx2 < 0) {
        __builtin_cpu_init();
        use_avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    }
    if (use_avx2)
        return row_avx2(kernel, g, w, s, k, lim);
#endif
    return row_scalar(kernel, g, w, s, k, lim);
}

/* Which row loop runs: 1 for AVX2, 0 for the portable one. */
int32_t dqm_simd_level(void)
{
    row_terms(KERNEL_GAUSSIAN, 0, 0, 0, 0, 0.0f);
    return use_avx2 > 0;
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
    if (use_avx2)
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
 * pairs written or -1 if more than cap.
 */
int64_t dqm_tile_sym(const float *G, int64_t m, int64_t k, int64_t ldg,
                     const float *wc, const float *sc, const float *wr, const float *sr,
                     int32_t kernel, const float *rad2r, const float *rad2c,
                     double *dens_r, double *err_r, double *dens_c, double *err_c,
                     float *cacc, float *cerr,
                     int32_t *cand_r, int32_t *cand_c, int64_t cap)
{
    int64_t count = 0;
    float cmax = 0.0f;
    row_terms(kernel, 0, 0, 0, 0, 0.0f); /* resolves use_avx2 */
    for (int64_t c = 0; c < k; ++c) {
        cacc[c] = 0.0f;
        cerr[c] = 0.0f;
        cmax = rad2c[c] > cmax ? rad2c[c] : cmax;
    }
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        float lim = rad2r[r] > cmax ? rad2r[r] : cmax;
        RowOut a = row_terms(kernel, g, wc, sc, k, lim);
        dens_r[r] += (double)a.acc;
        err_r[r] += (double)a.err;
        col_terms(kernel, g, wr[r], sr[r], k, cacc, cerr);
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
    for (int64_t c = 0; c < k; ++c) {
        dens_c[c] += (double)cacc[c];
        err_c[c] += (double)cerr[c];
    }
    return count;
}

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

/*
 * Nearest-neighbour tile of the distinctiveness pass: rows and columns are
 * features of one image (pass a tile whose self pairs are set to FLT_MAX;
 * entries equal to FLT_MAX are never reported).
 * Writes every row's and column's minimum over the tile and every (r, c) with
 * g <= rmin[r] + slack_r[r] or g <= cmin[c] + slack_c[c] (with its value), so
 * that the caller, knowing the global minima, can recompute those exactly.
 * Returns the count or -1 if more than cap.
 */
int64_t dqm_nearest_sym(const float *G, int64_t m, int64_t k, int64_t ldg,
                        const float *slack_r, const float *slack_c,
                        float *rmin, float *cmin,
                        int32_t *cand_r, int32_t *cand_c, float *cand_g, int64_t cap)
{
    row_terms(KERNEL_GAUSSIAN, 0, 0, 0, 0, 0.0f); /* resolves use_avx2 */
    for (int64_t c = 0; c < k; ++c)
        cmin[c] = FLT_MAX;
    for (int64_t r = 0; r < m; ++r) {
#ifdef DQM_HAVE_AVX2_PATH
        if (use_avx2) {
            rmin[r] = minrow_avx2(G + r * ldg, k, cmin);
            continue;
        }
#endif
        rmin[r] = minrow_scalar(G + r * ldg, k, cmin);
    }
    /* column limits once */
    int64_t count = 0;
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        float lr = rmin[r] + slack_r[r];
        for (int64_t c = 0; c < k; ++c) {
            float v = g[c];
            if (v < FLT_MAX && (v <= lr || v <= cmin[c] + slack_c[c])) {
                if (count >= cap)
                    return -1;
                cand_r[count] = (int32_t)r;
                cand_c[count] = (int32_t)c;
                cand_g[count] = v;
                ++count;
            }
        }
    }
    return count;
}

/*
 * self_col: for row r the column holding the same feature is r + self_col when
 * 0 <= r + self_col < k (pass a value <= -m or >= k when the tile holds no
 * self pair). Returns the number of candidate pairs written, or -1 when more
 * than cap were found (the caller retries the tile with a larger buffer).
 */
int64_t dqm_tile(const float *G, int64_t m, int64_t k, int64_t ldg,
                 const float *w, const float *s, int32_t kernel, const float *rad2,
                 int64_t self_col, double *dens, double *err,
                 int32_t *cand_r, int32_t *cand_c, int64_t cap)
{
    int64_t count = 0;
    for (int64_t r = 0; r < m; ++r) {
        const float *g = G + r * ldg;
        float lim = rad2[r];
        int64_t sc = r + self_col;
        int has_self = (sc >= 0 && sc < k);
        /* the self column is skipped, not subtracted: subtracting ~1 from a
           float sum would lose the small terms of isolated features */
        RowOut a = row_terms(kernel, g, w, s, has_self ? sc : k, lim);
        if (has_self) {
            RowOut b = row_terms(kernel, g + sc + 1, w + sc + 1, s + sc + 1, k - sc - 1, lim);
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
