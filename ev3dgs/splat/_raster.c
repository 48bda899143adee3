/* The `cpu` backend's tile kernels in C with 8-lane SIMD (float32): see ev3dgs/splat/cpu_simd.py.
 *
 * The kernel body (after the #else at the end of this file) is compiled twice by including this file into
 * itself: on x86 once for AVX2 (every function with __attribute__((target("avx2"))), 256-bit ymm registers)
 * and everywhere once for the baseline of the compiler's target (SSE2 on x86_64, where the compiler splits
 * each 8-lane operation into two xmm ones; NEON on aarch64); the AVX2 build is chosen at run time with
 * __builtin_cpu_supports. Compiled with -ffp-contract=off and no FMA,
 * every lane does the same IEEE float32 operations in the same order in both builds, so the two give
 * bitwise the same results (tested), and the per-pixel sigma, alpha and transmittance are bitwise those of
 * the numba kernel: only exp(-sigma) differs (exp_neg below, relative error <= 2^-22 against ~2^-24 for the
 * library's expf), the order in which a Gaussian's per-pixel gradients are summed (8 lane accumulators) and
 * the backward's (colour behind) . G, one running sum instead of one colour behind per channel.
 */
#ifndef RASTER_BODY
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#define TILE 16
#define NPIX (TILE * TILE)
#define DMAX 8            /* colour channels served (more: the numba kernel) */
#define MAX_THREADS 256

typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
typedef float v8fu __attribute__((vector_size(32), aligned(4)));   /* unaligned loads / stores */
typedef int32_t v8iu __attribute__((vector_size(32), aligned(4)));
typedef float v4f __attribute__((vector_size(16)));
#define PAD 8             /* tile arrays run 8 past the last pixel: a lane group may start at column 15 */

/* One call's arrays (C-contiguous, float32 unless stated); filled by cpu_simd.Job (ctypes). */
typedef struct {
    const float *params;       /* (K, 7 + D): mx, my, a, b, c, opacity, sigma_max, colour... (cpu_tiles._pack) */
    const int32_t *boxes;      /* (K, 4): x0, x1, y0, y1 of the entry's pixel box in its tile */
    const int64_t *offsets;    /* (C * n_tiles + 1,) */
    const int64_t *work;       /* (n_work,) global tiles, most expensive first (cpu._work_order) */
    int64_t n_work;
    const float *background;   /* (D,) */
    int64_t D, width, height, tiles_x, n_tiles;
    float *image;              /* (C, H, W, D) */
    float *t_final;            /* (C, H, W) */
    int64_t *last;             /* (C, H, W) */
    const int64_t *frag_start; /* (K + 1,) slots of entry k: frag_start[k] ... (8 per box row and lane group) */
    float *frag_e;             /* exp(-sigma) of a composited fragment, 0 elsewhere */
    int32_t *frag_n;           /* (K,) fragments entry k composited */
    int64_t record;            /* forward: record fragments; backward: replay them (else recompute) */
    const float *grad_image;   /* (C, H, W, D) */
    const float *grad_alpha;   /* (C, H, W) */
    float *per_pair;           /* (K, 6 + D) */
    int64_t n_threads;
    int64_t isa;               /* -1: best available, 0: portable build, 1: AVX2 (if the CPU has it) */
    int64_t *tile_ns;          /* NULL, or (C * n_tiles,): each tile's thread CPU time in ns (benchmarks) */
} job_t;

typedef void (*tile_fn)(const job_t *, int64_t);

#define RASTER_BODY 1
#if defined(__x86_64__) || defined(__i386__)
#define X86 1
#define SUF(name) name##_avx2
#define HAVE_AVX 1
#define TARGET __attribute__((target("avx2")))   /* GCC and clang; every function of the AVX2 build */
#include "_raster.c"
#undef SUF
#undef HAVE_AVX
#undef TARGET
#else
#define X86 0
#endif
#define SUF(name) name##_portable
#define HAVE_AVX 0
#define TARGET
#include "_raster.c"
#undef SUF
#undef HAVE_AVX
#undef TARGET

static int cpu_avx2(void)
{
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2");
#else
    return 0;
#endif
}

int ev3dgs_raster_isa(int64_t want)
{
    if (want == 0) return 0;
    return cpu_avx2() ? 1 : 0;
}

#if X86
#define PICK(name) (ev3dgs_raster_isa(job->isa) ? name##_avx2 : name##_portable)
#else
#define PICK(name) name##_portable
#endif

typedef struct {
    const job_t *job;
    tile_fn fn;
    int64_t *next;             /* shared: the next index of the work list to take */
} worker_t;

/* Each thread takes the next tile of the cost-sorted work list when it is free (a shared atomic counter: the
   list-scheduling a greedy longest-first deal approximates, without its imbalance when the list's order
   misjudges the costs). Which thread runs a tile does not change any result: tiles own their pixels and
   per-pair rows. */
static void *run_worker(void *arg)
{
    worker_t *w = arg;
    const job_t *job = w->job;
    for (int64_t i; (i = __atomic_fetch_add(w->next, 1, __ATOMIC_RELAXED)) < job->n_work;) {
        if (job->tile_ns) {
            struct timespec t0, t1;
            clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t0);
            w->fn(job, job->work[i]);
            clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t1);
            job->tile_ns[job->work[i]] = (t1.tv_sec - t0.tv_sec) * 1000000000LL + (t1.tv_nsec - t0.tv_nsec);
        } else {
            w->fn(job, job->work[i]);
        }
    }
    return NULL;
}

static int run(job_t *job, tile_fn fn)
{
    if (job->n_threads < 1) job->n_threads = 1;
    if (job->n_threads > MAX_THREADS) job->n_threads = MAX_THREADS;
    if (job->n_threads > job->n_work) job->n_threads = job->n_work > 0 ? job->n_work : 1;
    worker_t workers[MAX_THREADS];
    pthread_t tid[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    int64_t n = job->n_threads, next = 0;
    for (int64_t i = 0; i < n; i++) workers[i] = (worker_t){job, fn, &next};
    for (int64_t i = 1; i < n; i++) started[i] = pthread_create(&tid[i], NULL, run_worker, &workers[i]) == 0;
    run_worker(&workers[0]);
    for (int64_t i = 1; i < n; i++) {
        if (started[i]) pthread_join(tid[i], NULL);
        else run_worker(&workers[i]);             /* a thread that could not start: its share runs here */
    }
    return 0;
}

/* The ctypes entry points (called with the GIL released). Return 0, or -1 for D > DMAX. */
int ev3dgs_raster_forward(job_t *job)
{
    if (job->D < 1 || job->D > DMAX) return -1;
    return run(job, PICK(forward_tile));
}

int ev3dgs_raster_backward(job_t *job)
{
    if (job->D < 1 || job->D > DMAX) return -1;
    return run(job, PICK(backward_tile));
}

void ev3dgs_exp_neg(const float *s, float *out, int64_t n, int64_t isa)
{
#if X86
    if (ev3dgs_raster_isa(isa)) {
        exp_neg_array_avx2(s, out, n);
        return;
    }
#else
    (void)isa;
#endif
    exp_neg_array_portable(s, out, n);
}

static PyMethodDef methods[] = {{NULL, NULL, 0, NULL}};
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "ev3dgs.splat._raster",
                                    "The cpu backend's SIMD tile kernels (called through ctypes: see "
                                    "ev3dgs.splat.cpu_simd).", -1, methods, NULL, NULL, NULL, NULL};
PyMODINIT_FUNC PyInit__raster(void) { return PyModule_Create(&module); }

#else /* ------------------------------------------------------------------ kernel body, built twice -- */

static inline TARGET v8f SUF(bcast)(float x) { return (v8f){x, x, x, x, x, x, x, x}; }
static inline TARGET v8i SUF(ibcast)(int32_t x) { return (v8i){x, x, x, x, x, x, x, x}; }
/* a where m (all bits set), else b */
#if HAVE_AVX
static inline TARGET v8f SUF(sel)(v8i m, v8f a, v8f b) { return __builtin_ia32_blendvps256(b, a, (v8f)m); }
static inline TARGET v8i SUF(seli)(v8i m, v8i a, v8i b)
{
    return (v8i)__builtin_ia32_blendvps256((v8f)b, (v8f)a, (v8f)m);
}
#else
static inline TARGET v8f SUF(sel)(v8i m, v8f a, v8f b) { return (v8f)((m & (v8i)a) | (~m & (v8i)b)); }
static inline TARGET v8i SUF(seli)(v8i m, v8i a, v8i b) { return (m & a) | (~m & b); }
#endif

static inline TARGET int SUF(lanes)(v8i m)  /* bit i set: lane i's mask is set */
{
#if HAVE_AVX
    return __builtin_ia32_movmskps256((v8f)m);
#else
    int r = 0;
    for (int i = 0; i < 8; i++) r |= (m[i] < 0) << i;
    return r;
#endif
}

/* exp(-s) for float32 s >= 0 (s > 87 gives exp(-87)); see cpu_simd.EXP_REL_ERROR for the error bound.
   x = -s = n ln2 + f with n = round(x / ln2) (the 1.5 * 2^23 shifter), f by Cody-Waite's two-part ln2
   (C1 has 9 significant bits: n C1 is exact), exp(f) = 1 + f + f^2 P(f) with Cephes' expf minimax
   coefficients on |f| <= ln2 / 2, times 2^n built in the exponent bits. */
static inline TARGET v8f SUF(exp_neg)(v8f s)
{
    v8f x = -s;
    x = SUF(sel)(x < SUF(bcast)(-87.0f), SUF(bcast)(-87.0f), x);
    v8f shifter = SUF(bcast)(12582912.0f);
    v8f r = (x * SUF(bcast)(1.44269504088896341f) + shifter) - shifter;
    v8f f = (x - r * SUF(bcast)(0.693359375f)) - r * SUF(bcast)(-2.12194440e-4f);
    /* P by Estrin's scheme (three independent pairs: a shorter dependency chain than Horner's) */
    v8f f2 = f * f;
    v8f q0 = SUF(bcast)(1.6666665459e-1f) * f + SUF(bcast)(5.0000001201e-1f);
    v8f q1 = SUF(bcast)(8.3334519073e-3f) * f + SUF(bcast)(4.1665795894e-2f);
    v8f q2 = SUF(bcast)(1.9875691500e-4f) * f + SUF(bcast)(1.3981999507e-3f);
    v8f p = q0 + f2 * (q1 + f2 * q2);
    v8f y = (p * f2 + f) + SUF(bcast)(1.0f);
    v8i n = __builtin_convertvector(r, v8i);
    v8f pow2 = (v8f)((n + SUF(ibcast)(127)) << 23);
    return y * pow2;
}

static TARGET void SUF(exp_neg_array)(const float *s, float *out, int64_t n)
{
    int64_t i = 0;
    for (; i + 8 <= n; i += 8) *(v8fu *)(out + i) = SUF(exp_neg)(*(const v8fu *)(s + i));
    if (i < n) {
        v8f t = SUF(bcast)(0.0f);
        for (int64_t j = i; j < n; j++) t[j - i] = s[j];
        t = SUF(exp_neg)(t);
        for (int64_t j = i; j < n; j++) out[j] = t[j - i];
    }
}

/* tile geometry: camera, origin, size */
#define TILE_GEOMETRY                                                                               \
    int64_t cam = gt / job->n_tiles, tile = gt % job->n_tiles;                                      \
    int64_t x0 = (tile % job->tiles_x) * TILE, y0 = (tile / job->tiles_x) * TILE;                   \
    int64_t w = job->width - x0 < TILE ? job->width - x0 : TILE;                                    \
    int64_t h = job->height - y0 < TILE ? job->height - y0 : TILE;                                  \
    int64_t stride = 7 + D;                                                                         \
    const v8i iota_i = {0, 1, 2, 3, 4, 5, 6, 7};                                                    \
    const v8f iota_f = {0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f};

/* The (row, lane group) items of an entry's box [bx0, bx1] x [by0, by1] as one loop: lanes gx ... gx + 7 of
   row py (dy, cdy = c dy^2 of that row), base = the first lane's index in the tile arrays. Its trip count is
   known at the entry, so the branch predictor misses about once per entry instead of once per row. */
#define ITEMS_BEGIN                                                                                 \
    {                                                                                               \
        int32_t gx_next = bx0, py = by0;                                                            \
        int64_t n_items = (int64_t)(by1 - by0 + 1) * ((bx1 - bx0) / 8 + 1);                         \
        v8f dy = SUF(bcast)((float)py - my), cdy = c * dy * dy;                                     \
        for (int64_t it = 0; it < n_items; it++) {                                                  \
            int32_t gx = gx_next;                                                                   \
            int64_t base = (py - y0) * TILE + (gx - x0);                                            \
            v8f dy_row = dy, cdy_row = cdy;                                                         \
            gx_next += 8;                                                                           \
            if (gx_next > bx1) {                                                                    \
                gx_next = bx0;                                                                      \
                py++;                                                                               \
                dy = SUF(bcast)((float)py - my);                                                    \
                cdy = c * dy * dy;                                                                  \
            }                                                                                       \
            {                                                                                       \
                v8f dy = dy_row, cdy = cdy_row;
#define ITEMS_END                                                                                   \
            }                                                                                       \
        }                                                                                           \
    }

/* Per tile: entries in depth order; per box row and group of 8 pixels (from the box's first column) all lanes
   at once, the same rules as cpu._forward, with masks: a lane composites when it is inside the box, its pixel
   not done, 0 <= sigma <= sigma_max, alpha >= 1/255 and T (1 - alpha) >= 1e-4 (below: the pixel is done). */
static inline __attribute__((always_inline)) TARGET void SUF(forward_impl)(const job_t *job, int64_t gt,
                                                                          const int64_t D)
{
    TILE_GEOMETRY
    const v8f half = SUF(bcast)(0.5f), one = SUF(bcast)(1.0f), amax = SUF(bcast)(0.99f);
    const v8f amin = SUF(bcast)((float)(1.0 / 255.0)), tmin = SUF(bcast)(1e-4f), zero = SUF(bcast)(0.0f);
    _Alignas(32) float T[NPIX + PAD];
    _Alignas(32) float C[DMAX * NPIX + PAD];
    _Alignas(32) int32_t stop[NPIX + PAD];
    _Alignas(32) int32_t done[NPIX + PAD];
    for (int p = 0; p < NPIX + PAD; p++) {
        T[p] = 1.0f;
        stop[p] = 0;
        done[p] = 0;
    }
    memset(C, 0, sizeof(float) * (size_t)(D * NPIX + PAD));
    int64_t n_done = 0, P = w * h;
    int64_t start = job->offsets[gt], end = job->offsets[gt + 1];
    int64_t k = start;
    for (; k < end; k++) {
        if (n_done == P) break;                /* every pixel done: nothing later is composited */
        const float *q = job->params + k * stride;
        const int32_t *bx = job->boxes + 4 * k;
        int32_t bx0 = bx[0], bx1 = bx[1], by0 = bx[2], by1 = bx[3];
        int32_t nf = 0;
        if (bx0 <= bx1 && by0 <= by1) {
            float mx = q[0], my = q[1];
            v8f a = SUF(bcast)(q[2]), b = SUF(bcast)(q[3]), c = SUF(bcast)(q[4]), o = SUF(bcast)(q[5]);
            v8f smax = SUF(bcast)(q[6]);
            v8f col[DMAX];
            for (int64_t d = 0; d < D; d++) col[d] = SUF(bcast)(q[7 + d]);
            v8i kk = SUF(ibcast)((int32_t)(k + 1 - start));
            v8i hi = SUF(ibcast)(bx1);
            float *fe = job->record ? job->frag_e + job->frag_start[k] : NULL;
            ITEMS_BEGIN
                    v8i lane_i = SUF(ibcast)(gx) + iota_i;
                    v8f dx = (SUF(bcast)((float)gx) + iota_f) - SUF(bcast)(mx);
                    v8f sigma = half * (a * dx * dx + cdy) + b * dx * dy;
                    v8i dn = *(v8iu *)(done + base);
                    v8i m = (lane_i <= hi) & ~dn & (sigma >= zero) & (sigma <= smax);
                    if (!SUF(lanes)(m)) {  /* nothing to composite: no exp (most groups on dense scenes) */
                        if (fe) {
                            *(v8fu *)fe = zero;
                            fe += 8;
                        }
                        continue;
                    }
                    v8f e = SUF(exp_neg)(sigma);
                    v8f raw = o * e;
                    v8f alpha = SUF(sel)(raw < amax, raw, amax);
                    m &= alpha >= amin;
                    v8f t = *(v8fu *)(T + base);
                    v8f nt = t * (one - alpha);
                    v8i term = m & (nt < tmin);
                    int bits = SUF(lanes)(term);
                    if (bits) {
                        *(v8iu *)(done + base) = dn | term;
                        n_done += __builtin_popcount(bits);
                        m &= ~term;
                    }
                    /* weight 0 in the lanes that do not composite: C + colour * 0 = C (C >= +0 or a sum) */
                    v8f wgt = SUF(sel)(m, alpha, zero) * t;
                    for (int64_t d = 0; d < D; d++) {
                        v8fu *cd = (v8fu *)(C + d * NPIX + base);
                        *cd = *cd + col[d] * wgt;
                    }
                    *(v8fu *)(T + base) = SUF(sel)(m, nt, t);
                    *(v8iu *)(stop + base) = SUF(seli)(m, kk, *(v8iu *)(stop + base));
                    if (fe) {
                        *(v8fu *)fe = SUF(sel)(m, e, zero);
                        fe += 8;
                        nf += __builtin_popcount(SUF(lanes)(m));
                    }
            ITEMS_END
        }
        if (job->record) job->frag_n[k] = nf;
    }
    if (job->record)
        for (; k < end; k++) job->frag_n[k] = 0;  /* after the tile finished: no fragments */
    const float *bg = job->background;
    for (int64_t ly = 0; ly < h; ly++)
        for (int64_t lx = 0; lx < w; lx++) {
            int64_t p = ly * TILE + lx, pix = (cam * job->height + y0 + ly) * job->width + x0 + lx;
            for (int64_t d = 0; d < D; d++) job->image[pix * D + d] = C[d * NPIX + p] + T[p] * bg[d];
            job->t_final[pix] = T[p];
            job->last[pix] = stop[p] ? start + stop[p] : 0;
        }
}

/* lanes summed in a fixed order: a tree, ((0 + 4) + (2 + 6)) + ((1 + 5) + (3 + 7)) */
static inline TARGET float SUF(hsum)(v8f v)
{
    v4f lo = {v[0], v[1], v[2], v[3]}, hi = {v[4], v[5], v[6], v[7]};
    v4f s = lo + hi;
    return (s[0] + s[2]) + (s[1] + s[3]);
}

/* Per tile: entries in reverse depth order, the same (row, lane group) grid as the forward; a lane is a
   fragment where the recorded exp(-sigma) is not 0 (replay) or where the forward's tests pass for an entry
   before the pixel's stop (recompute: the same set, the same e, so bitwise the same gradients). The
   gradients of cpu_backward._fragment_grad per lane, summed per entry over the lanes in a fixed order. */
static inline __attribute__((always_inline)) TARGET void SUF(backward_impl)(const job_t *job, int64_t gt,
                                                                    const int64_t D)
{
    TILE_GEOMETRY
    const v8f half = SUF(bcast)(0.5f), one = SUF(bcast)(1.0f), amax = SUF(bcast)(0.99f);
    const v8f amin = SUF(bcast)((float)(1.0 / 255.0)), zero = SUF(bcast)(0.0f);
    _Alignas(32) float T[NPIX + PAD], GAT[NPIX + PAD], SG[NPIX + PAD];
    _Alignas(32) float G[DMAX * NPIX + PAD];
    _Alignas(32) int32_t stop[NPIX + PAD];
    int64_t start = job->offsets[gt], end = job->offsets[gt + 1], kmax = start;
    for (int p = 0; p < NPIX + PAD; p++) {
        T[p] = GAT[p] = SG[p] = 0.0f;
        stop[p] = 0;
    }
    memset(G, 0, sizeof(float) * (size_t)(D * NPIX + PAD));
    for (int64_t ly = 0; ly < h; ly++)
        for (int64_t lx = 0; lx < w; lx++) {
            int64_t p = ly * TILE + lx, pix = (cam * job->height + y0 + ly) * job->width + x0 + lx;
            T[p] = job->t_final[pix];
            int64_t s = job->last[pix];
            stop[p] = s > start ? (int32_t)(s - start) : 0;
            if (s > kmax) kmax = s;
            GAT[p] = job->grad_alpha[pix] * T[p];
            for (int64_t d = 0; d < D; d++) {
                G[d * NPIX + p] = job->grad_image[pix * D + d];
                SG[p] = SG[p] + T[p] * job->background[d] * G[d * NPIX + p];
            }
        }
    if (kmax > end) kmax = end;
    for (int64_t k = kmax - 1; k >= start; k--) {
        if (job->record && job->frag_n[k] == 0) continue;  /* per_pair[k] stays 0 */
        const float *q = job->params + k * stride;
        const int32_t *bx = job->boxes + 4 * k;
        int32_t bx0 = bx[0], bx1 = bx[1], by0 = bx[2], by1 = bx[3];
        if (bx0 > bx1 || by0 > by1) continue;
        float mx = q[0], my = q[1];
        v8f a = SUF(bcast)(q[2]), b = SUF(bcast)(q[3]), c = SUF(bcast)(q[4]), o = SUF(bcast)(q[5]);
        v8f smax = SUF(bcast)(q[6]);
        v8f col[DMAX], gcol[DMAX];
        for (int64_t d = 0; d < D; d++) {
            col[d] = SUF(bcast)(q[7 + d]);
            gcol[d] = zero;
        }
        v8f gmx = zero, gmy = zero, ga = zero, gb = zero, gc = zero, go = zero;
        v8i kk = SUF(ibcast)((int32_t)(k - start));
        v8i hi = SUF(ibcast)(bx1);
        const float *fe = job->record ? job->frag_e + job->frag_start[k] : NULL;
        ITEMS_BEGIN
                v8i lane_i = SUF(ibcast)(gx) + iota_i;
                v8f dx = (SUF(bcast)((float)gx) + iota_f) - SUF(bcast)(mx);
                v8f e;
                v8i m;
                if (fe) {
                    e = *(const v8fu *)fe;
                    fe += 8;
                    m = e != zero;
                    if (!SUF(lanes)(m)) continue;
                } else {
                    v8f sigma = half * (a * dx * dx + cdy) + b * dx * dy;
                    m = (lane_i <= hi) & (kk < *(v8iu *)(stop + base)) & (sigma >= zero) & (sigma <= smax);
                    if (!SUF(lanes)(m)) continue;
                    e = SUF(exp_neg)(sigma);
                    v8f raw = o * e;
                    m &= SUF(sel)(raw < amax, raw, amax) >= amin;
                    if (!SUF(lanes)(m)) continue;
                    e = SUF(sel)(m, e, zero);
                }
                v8f raw = o * e;
                v8f alpha = SUF(sel)(raw < amax, raw, amax);
                v8f inv = one / (one - alpha);
                v8f t = *(v8fu *)(T + base);
                v8f ti = t * inv;
                v8f wgt = alpha * ti;
                v8f cg = zero;
                /* lanes without a fragment have e = alpha = wgt = 0 and inv = 1: their T and SG stay as they
                   are and they add +-0 to every accumulator (finite inputs) */
                for (int64_t d = 0; d < D; d++) {
                    v8f gd = *(v8fu *)(G + d * NPIX + base);
                    gcol[d] += wgt * gd;
                    cg = cg + col[d] * gd;
                }
                /* SG = (colour behind) . G, kept as one sum: the colour behind grows by colour * wgt, so its
                   product with G grows by cg * wgt (no per-channel colour behind) */
                v8fu *sgp = (v8fu *)(SG + base);
                v8f sg = *sgp;
                v8f d_alpha = ti * cg - (sg - *(v8fu *)(GAT + base)) * inv;
                *sgp = sg + cg * wgt;
                *(v8fu *)(T + base) = ti;
                v8i gm = m & ~(raw > amax);     /* clamped alpha: no gradient to opacity or footprint */
                v8f d_sigma = -d_alpha * SUF(sel)(gm, alpha, zero);
                gmx = gmx - d_sigma * (a * dx + b * dy);
                gmy = gmy - d_sigma * (c * dy + b * dx);
                ga = ga + d_sigma * half * dx * dx;
                gb = gb + d_sigma * dx * dy;
                gc = gc + d_sigma * half * dy * dy;
                go = go + d_alpha * SUF(sel)(gm, e, zero);
        ITEMS_END
        float *pp = job->per_pair + k * (6 + D);
        pp[0] += SUF(hsum)(gmx);
        pp[1] += SUF(hsum)(gmy);
        pp[2] += SUF(hsum)(ga);
        pp[3] += SUF(hsum)(gb);
        pp[4] += SUF(hsum)(gc);
        pp[5] += SUF(hsum)(go);
        for (int64_t d = 0; d < D; d++) pp[6 + d] = SUF(hsum)(gcol[d]);
    }
}


/* D = 3 (RGB) compiled with the channel count known, every other D through the general loop */
static TARGET void SUF(forward_tile)(const job_t *job, int64_t gt)
{
    if (job->D == 3) SUF(forward_impl)(job, gt, 3);
    else SUF(forward_impl)(job, gt, job->D);
}

static TARGET void SUF(backward_tile)(const job_t *job, int64_t gt)
{
    if (job->D == 3) SUF(backward_impl)(job, gt, 3);
    else SUF(backward_impl)(job, gt, job->D);
}

#endif
