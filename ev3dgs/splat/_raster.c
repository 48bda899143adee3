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
#if !defined(RASTER_BODY) && !defined(PROJ_BODY)
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
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
    int64_t write_rows;        /* backward: per_pair's rows are written (every row, 0 without fragments) instead of
                                  added to (a zeroed buffer) */
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

/* ---- the records route's set-up and gradient sum (scalar: memory-bound passes over the entries) ---- */

/* recs (C * N, S) float32, 64-byte aligned by the caller: per camera and Gaussian one record, mx, my (means2d
   (C, N, 2)), a, b, c (conics (C, N, 3)), opacity and sigma_max ((N,)), its D colour channels (colours at
   col + c * col_cam_stride + g * D: stride 0 for colours shared by the cameras), then its pixel box (gboxes
   (C, N, 4) int32) as int32. One sequential pass; the kernels then read one record (one cache line for S = 16)
   per tile-list entry instead of _pack's copy. Returns the fragment slots the C kernels need for all the
   entries (ev3dgs_raster_prep's frag_start[K]): _bin puts a Gaussian in every tile its box touches, so its
   entries' boxes split its box by tile columns and rows: (rows) x (8 per group of 8 columns, per tile column). */
int64_t ev3dgs_raster_records(float *recs, int64_t S, int64_t C, int64_t N, int64_t D, const float *m2d,
                           const float *con, const float *col, int64_t col_cam_stride, const float *opac,
                           const float *smax, const int32_t *gbox)
{
    int64_t total = 0;
    for (int64_t c = 0; c < C; c++)
        for (int64_t g = 0; g < N; g++) {
            int64_t cg = c * N + g;
            float *r = recs + cg * S;
            r[0] = m2d[2 * cg];
            r[1] = m2d[2 * cg + 1];
            r[2] = con[3 * cg];
            r[3] = con[3 * cg + 1];
            r[4] = con[3 * cg + 2];
            r[5] = opac[g];
            r[6] = smax[g];
            for (int64_t d = 0; d < D; d++) r[7 + d] = col[c * col_cam_stride + g * D + d];
            const int32_t *b = gbox + 4 * cg;
            memcpy(r + 7 + D, b, 4 * sizeof(int32_t));
            for (int64_t j = 11 + D; j < S; j++) r[j] = 0.0f;
            if (b[0] > b[1] || b[2] > b[3]) continue;
            int64_t groups = 0;
            for (int64_t tx = b[0] / TILE; tx <= b[1] / TILE; tx++) {
                int64_t lo = b[0] > tx * TILE ? b[0] : tx * TILE;
                int64_t hi = b[1] < tx * TILE + TILE - 1 ? b[1] : tx * TILE + TILE - 1;
                groups += (hi - lo) / 8 + 1;
            }
            total += (int64_t)(b[3] - b[2] + 1) * groups * 8;
        }
    return total;
}

typedef struct {
    const int64_t *ids, *offsets;
    const float *recs;
    int64_t S, D, N, width, height, tiles_x, n_tiles, gt0, gt1;
    float *params;
    int32_t *boxes;
    int64_t *slots;            /* NULL, or (K + 1,): entry k's slot count at k + 1 */
} pack_t;

static void *pack_tiles(void *arg)
{
    const pack_t *p = arg;
    int64_t S = p->S, D = p->D, R = 7 + D;
    for (int64_t gt = p->gt0; gt < p->gt1; gt++) {
        int64_t cam = gt / p->n_tiles, tile = gt % p->n_tiles;
        int64_t x0 = (tile % p->tiles_x) * TILE, y0 = (tile / p->tiles_x) * TILE;
        int64_t w = p->width - x0 < TILE ? p->width - x0 : TILE, h = p->height - y0 < TILE ? p->height - y0 : TILE;
        const float *rec0 = p->recs + cam * p->N * S;
        for (int64_t k = p->offsets[gt], end = p->offsets[gt + 1]; k < end; k++) {
            if (k + 8 < end) __builtin_prefetch(rec0 + p->ids[k + 8] * S);
            const float *r = rec0 + p->ids[k] * S;
            float *q = p->params + k * R;
            for (int64_t j = 0; j < R; j++) q[j] = r[j];
            int32_t gb[4];
            memcpy(gb, r + R, sizeof gb);
            int32_t bx0 = gb[0] > x0 ? gb[0] : (int32_t)x0, bx1 = gb[1] < x0 + w - 1 ? gb[1] : (int32_t)(x0 + w - 1);
            int32_t by0 = gb[2] > y0 ? gb[2] : (int32_t)y0, by1 = gb[3] < y0 + h - 1 ? gb[3] : (int32_t)(y0 + h - 1);
            if (bx0 > bx1 || by0 > by1) bx0 = 0, bx1 = -1, by0 = 0, by1 = -1;
            int32_t *b = p->boxes + 4 * k;
            b[0] = bx0, b[1] = bx1, b[2] = by0, b[3] = by1;
            if (p->slots) p->slots[k + 1] = bx0 <= bx1 ? (int64_t)(by1 - by0 + 1) * ((bx1 - bx0) / 8 + 1) * 8 : 0;
        }
    }
    return NULL;
}

/* cpu_tiles._pack from the records: entry k's params row (mx, my, a, b, c, opacity, sigma_max, colour...: its
   Gaussian's record, copied) and its pixel box clipped to its tile ((0, -1, 0, -1) when empty), exactly
   _pack's values; with frag_start, the C kernels' fragment slots per entry (8 per row and group of 8 columns
   of the box, as cpu_simd.fragment_slots counts them): frag_start[k] ... frag_start[k + 1] - 1, and the
   total returned. One record gathered per entry (prefetched a few entries ahead) instead of six arrays;
   tiles split over n_threads threads in contiguous ranges of about equal entry counts. */
int64_t ev3dgs_raster_pack(const int64_t *ids, const int64_t *offsets, const float *recs, int64_t S, int64_t D,
                           int64_t C, int64_t N, int64_t width, int64_t height, int64_t tiles_x, float *params,
                           int32_t *boxes, int64_t *frag_start, int64_t n_threads)
{
    int64_t n_tiles = tiles_x * ((height + TILE - 1) / TILE), G = C * n_tiles, K = offsets[G];
    if (n_threads < 1) n_threads = 1;
    if (n_threads > MAX_THREADS) n_threads = MAX_THREADS;
    if (K < 65536) n_threads = 1;
    pack_t parts[MAX_THREADS];
    pthread_t tid[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    int64_t gt = 0;
    for (int64_t t = 0; t < n_threads; t++) {
        int64_t gt0 = gt, target = K * (t + 1) / n_threads;
        while (gt < G && offsets[gt + 1] <= target) gt++;
        if (t == n_threads - 1) gt = G;
        parts[t] = (pack_t){ids, offsets, recs, S, D, N, width, height, tiles_x, n_tiles, gt0, gt, params, boxes,
                            frag_start};
    }
    for (int64_t t = 1; t < n_threads; t++) started[t] = pthread_create(&tid[t], NULL, pack_tiles, &parts[t]) == 0;
    pack_tiles(&parts[0]);
    for (int64_t t = 1; t < n_threads; t++) {
        if (started[t]) pthread_join(tid[t], NULL);
        else pack_tiles(&parts[t]);
    }
    if (!frag_start) return 0;
    frag_start[0] = 0;
    for (int64_t k = 0; k < K; k++) frag_start[k + 1] += frag_start[k];
    return frag_start[K];
}

typedef struct {
    const float *per_pair;
    const int64_t *ids, *offsets;
    int64_t c0, c1, n_tiles, N, D;
    float *acc, *g_mean, *g_conic, *g_op, *g_col;
} reduce_t;

static void *reduce_cameras(void *arg)
{
    const reduce_t *r = arg;
    int64_t N = r->N, D = r->D, R = 6 + D;
    for (int64_t c = r->c0; c < r->c1; c++) {
        float *acc = r->acc + c * N * R;     /* one row of 6 + D sums per Gaussian: one or two cache lines */
        memset(acc, 0, sizeof(float) * (size_t)(N * R));
        for (int64_t k = r->offsets[c * r->n_tiles], end = r->offsets[(c + 1) * r->n_tiles]; k < end; k++) {
            float *a = acc + r->ids[k] * R;
            const float *pp = r->per_pair + k * R;
            for (int64_t j = 0; j < R; j++) a[j] += pp[j];
        }
        for (int64_t g = 0; g < N; g++) {
            const float *a = acc + g * R;
            int64_t cg = c * N + g;
            r->g_mean[2 * cg] = a[0];
            r->g_mean[2 * cg + 1] = a[1];
            r->g_conic[3 * cg] = a[2];
            r->g_conic[3 * cg + 1] = a[3];
            r->g_conic[3 * cg + 2] = a[4];
            r->g_op[cg] = a[5];
            for (int64_t d = 0; d < D; d++) r->g_col[cg * D + d] = a[6 + d];
        }
    }
    return NULL;
}

/* cpu_tiles._bin, serially (its lists do not depend on how it splits the work, so neither on this): per
   camera the visible Gaussians (radius > 0) in a stable depth order (an LSD radix sort on the keys of
   cpu_tiles._sort_keys, float32 depths: any stable sort on the same keys gives the same permutation), then
   counted and placed in every tile their pixel box (boxes (C, N, 4), floor division by TILE as numba's //)
   touches. ev3dgs_raster_bin_count writes orders (C, N) (the first n_vis[c] of row c: camera c's visible
   Gaussians front to back), their boxes in that order into sorted (C, N, 4) (read as a stream by both
   passes), n_vis (C,) and offsets (C * n_tiles + 1,) and returns the entry count (-1: out of memory);
   ev3dgs_raster_bin_place then fills ids (that many). */
static inline int64_t floor_tile(int64_t a) { return a >= 0 ? a / TILE : -((-a + TILE - 1) / TILE); }

int64_t ev3dgs_raster_bin_count(const int32_t *boxes, const int64_t *radii, const float *depths, int64_t C,
                                int64_t N, int64_t tiles_x, int64_t tiles_y, int64_t *orders, int64_t *n_vis,
                                int64_t *offsets, int32_t *sorted)
{
    int64_t n_tiles = tiles_x * tiles_y;
    uint32_t *keys = malloc((N > 0 ? N : 1) * sizeof(uint32_t));
    int64_t *tmp = malloc((N > 0 ? N : 1) * sizeof(int64_t));
    if (!keys || !tmp) {
        free(keys);
        free(tmp);
        return -1;
    }
    memset(offsets, 0, (C * n_tiles + 1) * sizeof(int64_t));
    for (int64_t c = 0; c < C; c++) {
        int64_t *order = orders + c * N, n = 0;
        for (int64_t g = 0; g < N; g++)
            if (radii[c * N + g] > 0) {
                uint32_t b;
                memcpy(&b, depths + c * N + g, sizeof b);
                keys[g] = (b & 0x80000000u) ? (b ^ 0xFFFFFFFFu) : (b | 0x80000000u);
                order[n++] = g;
            }
        n_vis[c] = n;
        for (int p = 0; p < 4; p++) {
            int64_t count[257] = {0};
            int shift = 8 * p;
            for (int64_t i = 0; i < n; i++) count[((keys[order[i]] >> shift) & 0xFF) + 1]++;
            int same = 0;
            for (int b = 1; b <= 256; b++) same |= count[b] == n;
            if (same) continue; /* every key has this byte: the pass would not move anything */
            for (int b = 0; b < 256; b++) count[b + 1] += count[b];
            for (int64_t i = 0; i < n; i++) {
                int64_t j = order[i];
                tmp[count[(keys[j] >> shift) & 0xFF]++] = j;
            }
            memcpy(order, tmp, n * sizeof(int64_t));
        }
        int64_t *cnt = offsets + c * n_tiles + 1;
        int32_t *bs = sorted + 4 * c * N;
        for (int64_t j = 0; j < n; j++) memcpy(bs + 4 * j, boxes + 4 * (c * N + order[j]), 4 * sizeof(int32_t));
        for (int64_t j = 0; j < n; j++) {
            const int32_t *b = bs + 4 * j;
            int64_t tx0 = floor_tile(b[0]), tx1 = floor_tile(b[1]), ty0 = floor_tile(b[2]), ty1 = floor_tile(b[3]);
            for (int64_t ty = ty0; ty <= ty1; ty++)
                for (int64_t tx = tx0; tx <= tx1; tx++) cnt[ty * tiles_x + tx]++;
        }
    }
    free(keys);
    free(tmp);
    for (int64_t gt = 0; gt < C * n_tiles; gt++) offsets[gt + 1] += offsets[gt];
    return offsets[C * n_tiles];
}

int ev3dgs_raster_bin_place(const int32_t *sorted, const int64_t *orders, const int64_t *n_vis, int64_t C,
                            int64_t N, int64_t tiles_x, int64_t tiles_y, const int64_t *offsets, int64_t *ids)
{
    int64_t n_tiles = tiles_x * tiles_y;
    int64_t *fill = malloc((n_tiles > 0 ? n_tiles : 1) * sizeof(int64_t));
    if (!fill) return -1;
    for (int64_t c = 0; c < C; c++) {
        memcpy(fill, offsets + c * n_tiles, n_tiles * sizeof(int64_t));
        const int64_t *order = orders + c * N;
        for (int64_t j = 0; j < n_vis[c]; j++) {
            int64_t g = order[j];
            const int32_t *b = sorted + 4 * (c * N + j);
            int64_t tx0 = floor_tile(b[0]), tx1 = floor_tile(b[1]), ty0 = floor_tile(b[2]), ty1 = floor_tile(b[3]);
            for (int64_t ty = ty0; ty <= ty1; ty++)
                for (int64_t tx = tx0; tx <= tx1; tx++) ids[fill[ty * tiles_x + tx]++] = g;
        }
    }
    free(fill);
    return 0;
}

/* cpu_backward._reduce: per camera a serial sum of the entries' rows in tile-list order (the same float32
   additions in the same order, from 0: bitwise its result), into one row of sums per Gaussian (acc, (C, N,
   6 + D) scratch), then split into g_mean (C, N, 2), g_conic (C, N, 3), g_op (C, N), g_col (C, N, D).
   Cameras split over up to n_threads threads (each camera's sum is one thread's). */
int ev3dgs_raster_reduce(const float *per_pair, const int64_t *ids, const int64_t *offsets, int64_t C,
                         int64_t n_tiles, int64_t N, int64_t D, float *acc, float *g_mean, float *g_conic,
                         float *g_op, float *g_col, int64_t n_threads)
{
    if (D < 1 || D > DMAX) return -1;
    if (n_threads > C) n_threads = C;
    if (n_threads < 1) n_threads = 1;
    if (n_threads > MAX_THREADS) n_threads = MAX_THREADS;
    reduce_t parts[MAX_THREADS];
    pthread_t tid[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int64_t t = 0; t < n_threads; t++)
        parts[t] = (reduce_t){per_pair, ids, offsets, C * t / n_threads, C * (t + 1) / n_threads, n_tiles, N, D,
                              acc, g_mean, g_conic, g_op, g_col};
    for (int64_t t = 1; t < n_threads; t++) started[t] = pthread_create(&tid[t], NULL, reduce_cameras, &parts[t]) == 0;
    reduce_cameras(&parts[0]);
    for (int64_t t = 1; t < n_threads; t++) {
        if (started[t]) pthread_join(tid[t], NULL);
        else reduce_cameras(&parts[t]);
    }
    return 0;
}

/* ---- projection + SH colours (float32 inputs, float64 arithmetic): project_cpu's kernels in C ---- */
/* The numba kernels project_cpu._project_forward / _project_backward written out in C: the same float64 operations
   in the same order (compiled with -ffp-contract=off: no fused multiply-adds), the same libm log and ceil, IEEE
   sqrt, so every output is bitwise theirs (tested). The scalar code below serves the last few Gaussians of a
   range; the rest run 4 at a time in float64 lanes (the projection body at the end of this file, built for AVX2
   and the baseline like the tile kernels): each lane does the scalar code's operations, its branches turned into
   selects of the value the scalar code keeps. Gaussians split over threads in contiguous ranges (the backward in
   blocks of VM_BLOCK, whose camera-gradient partial sums are per block): the result does not depend on the thread
   count. Inputs float32 (the trainer's dtype), outputs float32 (rounded from the float64 result, as the numba
   path's float32 outputs and .to(float32) conversions round). */
#include <math.h>

#define VM_BLOCK 256
static const double SH_C0 = 0.28209479177387814, SH_C1 = 0.4886025119029199;
static const double SH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                                0.5462742152960396};
static const double SH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                                -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

typedef struct {
    const float *means, *quats, *scales, *opac, *sh;  /* (N,3) (N,4) (N,3) (N,) (N,KS,3) */
    int64_t N, C, KS, deg, width, height;
    const double *vm, *campos, *cam;                  /* (C,4,4) (C,3) (C,8) */
    double near_, far_, eps2d, alpha_min, radius_margin;
    float *means2d, *conics, *depths, *colors;        /* forward outputs (C,N,2) (C,N,3) (C,N) (C,N,3) */
    int32_t *radii;                                   /* (C,N) */
    const float *g_m2d, *g_con, *g_dep, *g_col;       /* backward inputs (C,N,2) (C,N,3) (C,N) (C,N,3) */
    float *g_means, *g_quats, *g_scales, *g_sh;       /* backward outputs (N,3) (N,4) (N,3) (N,KS,3) */
    int64_t want_vm;
    double *g_vm;                                     /* (blocks, C, 15) */
    int64_t n_threads;
    int64_t isa;                                      /* as job_t's */
} proj_t;

/* Python's max(a, b) / min(a, b) on floats (the first argument unless the second compares greater/less) */
static inline double pmax(double a, double b) { return b > a ? b : a; }
static inline double pmin(double a, double b) { return b < a ? b : a; }
static inline int finite_d(double x) { return isfinite(x); }

static void rotmat(double qw, double qx, double qy, double qz, double r[9])
{
    r[0] = 1.0 - 2.0 * (qy * qy + qz * qz); r[1] = 2.0 * (qx * qy - qw * qz); r[2] = 2.0 * (qx * qz + qw * qy);
    r[3] = 2.0 * (qx * qy + qw * qz); r[4] = 1.0 - 2.0 * (qx * qx + qz * qz); r[5] = 2.0 * (qy * qz - qw * qx);
    r[6] = 2.0 * (qx * qz - qw * qy); r[7] = 2.0 * (qy * qz + qw * qx); r[8] = 1.0 - 2.0 * (qx * qx + qy * qy);
}

static void sh_basis(int64_t deg, double x, double y, double z, double *out)
{
    out[0] = SH_C0;
    if (deg >= 1) {
        out[1] = -SH_C1 * y;
        out[2] = SH_C1 * z;
        out[3] = -SH_C1 * x;
    }
    if (deg >= 2) {
        double xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
        out[4] = SH_C2[0] * xy;
        out[5] = SH_C2[1] * yz;
        out[6] = SH_C2[2] * (2.0 * zz - xx - yy);
        out[7] = SH_C2[3] * xz;
        out[8] = SH_C2[4] * (xx - yy);
        if (deg >= 3) {
            out[9] = SH_C3[0] * y * (3.0 * xx - yy);
            out[10] = SH_C3[1] * xy * z;
            out[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
            out[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            out[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
            out[14] = SH_C3[5] * z * (xx - yy);
            out[15] = SH_C3[6] * x * (xx - 3.0 * yy);
        }
    }
}

static void sh_basis_vjp(int64_t deg, double x, double y, double z, const double *gb, double *ox, double *oy,
                         double *oz)
{
    double gx = 0.0, gy = 0.0, gz = 0.0, g;
    if (deg >= 1) {
        gy -= SH_C1 * gb[1];
        gz += SH_C1 * gb[2];
        gx -= SH_C1 * gb[3];
    }
    if (deg >= 2) {
        double xx = x * x, yy = y * y, zz = z * z;
        g = SH_C2[0] * gb[4]; gx += g * y; gy += g * x;
        g = SH_C2[1] * gb[5]; gy += g * z; gz += g * y;
        g = SH_C2[2] * gb[6]; gx -= 2.0 * g * x; gy -= 2.0 * g * y; gz += 4.0 * g * z;
        g = SH_C2[3] * gb[7]; gx += g * z; gz += g * x;
        g = SH_C2[4] * gb[8]; gx += 2.0 * g * x; gy -= 2.0 * g * y;
        if (deg >= 3) {
            g = SH_C3[0] * gb[9]; gx += g * 6.0 * x * y; gy += g * (3.0 * xx - 3.0 * yy);
            g = SH_C3[1] * gb[10]; gx += g * y * z; gy += g * x * z; gz += g * x * y;
            g = SH_C3[2] * gb[11]; gx -= g * 2.0 * x * y; gy += g * (4.0 * zz - xx - 3.0 * yy); gz += g * 8.0 * y * z;
            g = SH_C3[3] * gb[12]; gx -= g * 6.0 * x * z; gy -= g * 6.0 * y * z;
            gz += g * (6.0 * zz - 3.0 * xx - 3.0 * yy);
            g = SH_C3[4] * gb[13]; gx += g * (4.0 * zz - 3.0 * xx - yy); gy -= g * 2.0 * x * y; gz += g * 8.0 * x * z;
            g = SH_C3[5] * gb[14]; gx += g * 2.0 * x * z; gy -= g * 2.0 * y * z; gz += g * (xx - yy);
            g = SH_C3[6] * gb[15]; gx += g * (3.0 * xx - 3.0 * yy); gy -= g * 6.0 * x * y;
        }
    }
    *ox = gx, *oy = gy, *oz = gz;
}

static int finite_row(const proj_t *p, int64_t n)
{
    int ok = finite_d(p->opac[n]);
    for (int i = 0; i < 3; i++) ok = ok && finite_d(p->means[3 * n + i]) && finite_d(p->scales[3 * n + i]);
    for (int i = 0; i < 4; i++) ok = ok && finite_d(p->quats[4 * n + i]);
    return ok;
}

typedef struct {
    double px, py, pz, qw, qx, qy, qz, inv, sq, sx, sy, sz;
} ginputs_t;

static void inputs(const proj_t *p, int64_t n, int finite, ginputs_t *g)
{
    if (finite) {
        g->px = p->means[3 * n], g->py = p->means[3 * n + 1], g->pz = p->means[3 * n + 2];
        g->qw = p->quats[4 * n], g->qx = p->quats[4 * n + 1], g->qy = p->quats[4 * n + 2], g->qz = p->quats[4 * n + 3];
        g->sx = p->scales[3 * n], g->sy = p->scales[3 * n + 1], g->sz = p->scales[3 * n + 2];
    } else {
        g->px = g->py = g->pz = 0.0;
        g->qw = g->qx = g->qy = g->qz = 1.0;
        g->sx = g->sy = g->sz = 1.0;
    }
    g->sq = g->qw * g->qw + g->qx * g->qx + g->qy * g->qy + g->qz * g->qz;
    g->inv = 1.0 / sqrt(pmax(g->sq, 1e-24));
}

static void sigma3(const ginputs_t *g, double r[9], double m[9], double S[9])
{
    rotmat(g->qw * g->inv, g->qx * g->inv, g->qy * g->inv, g->qz * g->inv, r);
    m[0] = r[0] * g->sx, m[1] = r[1] * g->sy, m[2] = r[2] * g->sz;
    m[3] = r[3] * g->sx, m[4] = r[4] * g->sy, m[5] = r[5] * g->sz;
    m[6] = r[6] * g->sx, m[7] = r[7] * g->sy, m[8] = r[8] * g->sz;
    double s00 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
    double s01 = m[0] * m[3] + m[1] * m[4] + m[2] * m[5];
    double s02 = m[0] * m[6] + m[1] * m[7] + m[2] * m[8];
    double s11 = m[3] * m[3] + m[4] * m[4] + m[5] * m[5];
    double s12 = m[3] * m[6] + m[4] * m[7] + m[5] * m[8];
    double s22 = m[6] * m[6] + m[7] * m[7] + m[8] * m[8];
    S[0] = s00, S[1] = s01, S[2] = s02, S[3] = s01, S[4] = s11, S[5] = s12, S[6] = s02, S[7] = s12, S[8] = s22;
}

typedef struct {
    double x, y, zr, z, xz, yz, cxz, cyz;
    int valid;
} camp_t;

static void camera_point(const proj_t *p, int64_t c, const ginputs_t *g, int finite, camp_t *o)
{
    const double *v = p->vm + 16 * c, *cam = p->cam + 8 * c;
    o->x = v[0] * g->px + v[1] * g->py + v[2] * g->pz + v[3];
    o->y = v[4] * g->px + v[5] * g->py + v[6] * g->pz + v[7];
    o->zr = v[8] * g->px + v[9] * g->py + v[10] * g->pz + v[11];
    o->valid = o->zr > p->near_ && o->zr < p->far_ && finite;
    o->z = o->valid ? o->zr : 1.0;
    o->xz = o->x / o->z, o->yz = o->y / o->z;
    o->cxz = pmin(pmax(o->xz, -cam[4]), cam[5]);
    o->cyz = pmin(pmax(o->yz, -cam[6]), cam[7]);
}

static double jw(const proj_t *p, int64_t c, double fx, double fy, double z, double tx, double ty, double t0[3],
                 double t1[3])
{
    const double *v = p->vm + 16 * c;
    double rz = 1.0 / z;
    double j00 = fx * rz, j02 = -fx * tx * rz * rz, j11 = fy * rz, j12 = -fy * ty * rz * rz;
    t0[0] = j00 * v[0] + j02 * v[8], t0[1] = j00 * v[1] + j02 * v[9], t0[2] = j00 * v[2] + j02 * v[10];
    t1[0] = j11 * v[4] + j12 * v[8], t1[1] = j11 * v[5] + j12 * v[9], t1[2] = j11 * v[6] + j12 * v[10];
    return rz;
}

static void cov2d(const double t0[3], const double t1[3], const double S[9], double eps2d, double *c11, double *c12,
                  double *c22)
{
    double u0 = S[0] * t0[0] + S[1] * t0[1] + S[2] * t0[2];
    double u1 = S[3] * t0[0] + S[4] * t0[1] + S[5] * t0[2];
    double u2 = S[6] * t0[0] + S[7] * t0[1] + S[8] * t0[2];
    double v0 = S[0] * t1[0] + S[1] * t1[1] + S[2] * t1[2];
    double v1 = S[3] * t1[0] + S[4] * t1[1] + S[5] * t1[2];
    double v2 = S[6] * t1[0] + S[7] * t1[1] + S[8] * t1[2];
    *c11 = t0[0] * u0 + t0[1] * u1 + t0[2] * u2 + eps2d;
    *c12 = t0[0] * v0 + t0[1] * v1 + t0[2] * v2;
    *c22 = t1[0] * v0 + t1[1] * v1 + t1[2] * v2 + eps2d;
}

/* numba's int(math.ceil(v)) then float: x86's conversion of an out-of-range or NaN value, INT64_MIN */
static double ceil_as_int(double v)
{
    double c = ceil(v);
    return (c >= -9223372036854775808.0 && c < 9223372036854775808.0) ? (double)(int64_t)c : -9223372036854775808.0;
}

typedef struct {
    const proj_t *p;
    int64_t lo, hi;
} prange_t;

static void *project_forward_range(void *arg)
{
    const prange_t *rg = arg;
    const proj_t *p = rg->p;
    int64_t N = p->N, C = p->C, deg = p->deg, K = (deg + 1) * (deg + 1), KS = p->KS;
    double basis[16];
    for (int64_t n = rg->lo; n < rg->hi; n++) {
        int finite = finite_row(p, n);
        ginputs_t g;
        inputs(p, n, finite, &g);
        double r9[9], m9[9], S[9];
        sigma3(&g, r9, m9, S);
        double o = finite ? (double)p->opac[n] : 1.0;
        for (int64_t c = 0; c < C; c++) {
            const double *cam = p->cam + 8 * c;
            double fx = cam[0], fy = cam[1];
            camp_t cp;
            camera_point(p, c, &g, finite, &cp);
            double t0[3], t1[3], c11, c12, c22;
            jw(p, c, fx, fy, cp.z, cp.z * cp.cxz, cp.z * cp.cyz, t0, t1);
            cov2d(t0, t1, S, p->eps2d, &c11, &c12, &c22);
            double det = pmax(c11 * c22 - c12 * c12, 1e-12);
            int64_t cn = c * N + n;
            p->conics[3 * cn] = (float)(c22 / det);
            p->conics[3 * cn + 1] = (float)(-c12 / det);
            p->conics[3 * cn + 2] = (float)(c11 / det);
            double mx = fx * cp.xz + cam[2], my = fy * cp.yz + cam[3];
            p->means2d[2 * cn] = (float)mx;
            p->means2d[2 * cn + 1] = (float)my;
            p->depths[cn] = (float)cp.zr;
            double r = 0.0;
            if (cp.valid && finite && !(o < p->alpha_min)) {
                double extent = sqrt(2.0 * pmax(log(255.0 * o), 0.0));
                double mid = 0.5 * (c11 + c22);
                double lam = mid + sqrt(pmax(mid * mid - (c11 * c22 - c12 * c12), 0.1));
                r = ceil_as_int(extent * sqrt(pmax(lam, 0.0)) * (1.0 + p->radius_margin));
                if (!finite_d(r)) r = 0.0;
                else if (r < 1.0) r = 1.0;
                if (mx + r < -0.5 || mx - r > p->width - 0.5 || my + r < -0.5 || my - r > p->height - 0.5
                    || !finite_d(mx) || !finite_d(my))
                    r = 0.0;
            }
            p->radii[cn] = (int32_t)(int64_t)pmin(r, 1073741824.0);
            if (deg >= 0) {
                const double *cpos = p->campos + 3 * c;
                double dx = g.px - cpos[0], dy = g.py - cpos[1], dz = g.pz - cpos[2];
                double d2 = pmax(dx * dx + dy * dy + dz * dz, 1e-24);
                double di = 1.0 / sqrt(d2);
                sh_basis(deg, dx * di, dy * di, dz * di, basis);
                for (int ch = 0; ch < 3; ch++) {
                    double acc = 0.0;
                    for (int64_t k = 0; k < K; k++) acc += basis[k] * (double)p->sh[(n * KS + k) * 3 + ch];
                    p->colors[3 * cn + ch] = (float)pmax(acc + 0.5, 0.0);
                }
            }
        }
    }
    return NULL;
}

/* Gaussians n0 ... n1 - 1 of block blk */
static void project_backward_gaussians(const proj_t *p, int64_t blk, int64_t n0, int64_t n1)
{
    int64_t N = p->N, C = p->C, deg = p->deg, K = (deg + 1) * (deg + 1), KS = p->KS;
    double basis[16], gb[16], u[3], v[3], gS[9], gsh[16 * 3];
    {
        double *gvm = p->g_vm + blk * C * 15;
        for (int64_t n = n0; n < n1; n++) {
            int finite = finite_row(p, n);
            if (!finite) {  /* exactly zero gradient for the whole row */
                for (int i = 0; i < 3; i++) p->g_means[3 * n + i] = 0.0f, p->g_scales[3 * n + i] = 0.0f;
                for (int i = 0; i < 4; i++) p->g_quats[4 * n + i] = 0.0f;
                if (deg >= 0) memset(p->g_sh + n * KS * 3, 0, sizeof(float) * (size_t)(KS * 3));
                continue;
            }
            ginputs_t g;
            inputs(p, n, finite, &g);
            double r9[9], m9[9], S[9];
            sigma3(&g, r9, m9, S);
            double gpx = 0.0, gpy = 0.0, gpz = 0.0;
            for (int i = 0; i < 9; i++) gS[i] = 0.0;
            if (deg >= 0)
                for (int i = 0; i < 48; i++) gsh[i] = 0.0;
            for (int64_t c = 0; c < C; c++) {
                const double *cam = p->cam + 8 * c, *vm = p->vm + 16 * c;
                double fx = cam[0], fy = cam[1];
                camp_t cp;
                camera_point(p, c, &g, finite, &cp);
                double z = cp.z, x = cp.x, y = cp.y, xz = cp.xz, yz = cp.yz, cxz = cp.cxz, cyz = cp.cyz;
                double tx = z * cxz, ty = z * cyz;
                double t0[3], t1[3], c11, c12, c22;
                double rz = jw(p, c, fx, fy, z, tx, ty, t0, t1);
                cov2d(t0, t1, S, p->eps2d, &c11, &c12, &c22);
                double det_raw = c11 * c22 - c12 * c12;
                double det = pmax(det_raw, 1e-12);
                int64_t cn = c * N + n;
                double ga = p->g_con[3 * cn], gbb = p->g_con[3 * cn + 1], gc = p->g_con[3 * cn + 2];
                double g11 = gc / det, g12 = -gbb / det, g22 = ga / det;
                if (det_raw >= 1e-12) {
                    double gdet = -(ga * c22 - gbb * c12 + gc * c11) / (det * det);
                    g11 += gdet * c22;
                    g22 += gdet * c11;
                    g12 -= 2.0 * gdet * c12;
                }
                double h = 0.5 * g12;
                for (int i = 0; i < 3; i++)
                    for (int j = 0; j < 3; j++)
                        gS[i * 3 + j] += (g11 * t0[i] * t0[j] + h * (t0[i] * t1[j] + t1[i] * t0[j])
                                          + g22 * t1[i] * t1[j]);
                for (int i = 0; i < 3; i++) {
                    u[i] = S[i * 3] * t0[0] + S[i * 3 + 1] * t0[1] + S[i * 3 + 2] * t0[2];
                    v[i] = S[i * 3] * t1[0] + S[i * 3 + 1] * t1[1] + S[i * 3 + 2] * t1[2];
                }
                double gT0[3] = {2.0 * (g11 * u[0] + h * v[0]), 2.0 * (g11 * u[1] + h * v[1]),
                                 2.0 * (g11 * u[2] + h * v[2])};
                double gT1[3] = {2.0 * (h * u[0] + g22 * v[0]), 2.0 * (h * u[1] + g22 * v[1]),
                                 2.0 * (h * u[2] + g22 * v[2])};
                double gj00 = gT0[0] * vm[0] + gT0[1] * vm[1] + gT0[2] * vm[2];
                double gj02 = gT0[0] * vm[8] + gT0[1] * vm[9] + gT0[2] * vm[10];
                double gj11 = gT1[0] * vm[4] + gT1[1] * vm[5] + gT1[2] * vm[6];
                double gj12 = gT1[0] * vm[8] + gT1[1] * vm[9] + gT1[2] * vm[10];
                double grz = fx * gj00 + fy * gj11 - 2.0 * fx * tx * rz * gj02 - 2.0 * fy * ty * rz * gj12;
                double gtx = -fx * rz * rz * gj02;
                double gty = -fy * rz * rz * gj12;
                double gz = -grz * rz * rz + gtx * cxz + gty * cyz;
                double gxz = fx * (double)p->g_m2d[2 * cn];
                double gyz = fy * (double)p->g_m2d[2 * cn + 1];
                if (xz > -cam[4] && xz < cam[5]) gxz += gtx * z;
                if (yz > -cam[6] && yz < cam[7]) gyz += gty * z;
                double gx = gxz / z;
                double gy = gyz / z;
                gz -= (gxz * x + gyz * y) / (z * z);
                double gzr = (double)p->g_dep[cn] + (cp.valid ? gz : 0.0);
                gpx += vm[0] * gx + vm[4] * gy + vm[8] * gzr;
                gpy += vm[1] * gx + vm[5] * gy + vm[9] * gzr;
                gpz += vm[2] * gx + vm[6] * gy + vm[10] * gzr;
                if (p->want_vm) {
                    double j00 = fx * rz, j02 = -fx * tx * rz * rz, j11 = fy * rz, j12 = -fy * ty * rz * rz;
                    double *gv = gvm + c * 15;
                    for (int j = 0; j < 3; j++) {
                        double pj = j == 0 ? g.px : (j == 1 ? g.py : g.pz);
                        gv[j] += gx * pj + j00 * gT0[j];
                        gv[4 + j] += gy * pj + j11 * gT1[j];
                        gv[8 + j] += gzr * pj + j02 * gT0[j] + j12 * gT1[j];
                    }
                    gv[3] += gx;
                    gv[7] += gy;
                    gv[11] += gzr;
                }
                if (deg >= 0) {
                    const double *cpos = p->campos + 3 * c;
                    double dx = g.px - cpos[0], dy = g.py - cpos[1], dz = g.pz - cpos[2];
                    double d2r = dx * dx + dy * dy + dz * dz;
                    double d2 = pmax(d2r, 1e-24);
                    double di = 1.0 / sqrt(d2);
                    double ux = dx * di, uy = dy * di, uz = dz * di;
                    sh_basis(deg, ux, uy, uz, basis);
                    for (int64_t k = 0; k < K; k++) gb[k] = 0.0;
                    for (int ch = 0; ch < 3; ch++) {
                        double acc = 0.0;
                        for (int64_t k = 0; k < K; k++) acc += basis[k] * (double)p->sh[(n * KS + k) * 3 + ch];
                        if (acc + 0.5 >= 0.0) {
                            double gcol = p->g_col[3 * cn + ch];
                            for (int64_t k = 0; k < K; k++) {
                                gsh[k * 3 + ch] += basis[k] * gcol;
                                gb[k] += (double)p->sh[(n * KS + k) * 3 + ch] * gcol;
                            }
                        }
                    }
                    double gux, guy, guz;
                    sh_basis_vjp(deg, ux, uy, uz, gb, &gux, &guy, &guz);
                    double gdx = gux * di, gdy = guy * di, gdz = guz * di;
                    if (d2r >= 1e-24) {
                        double dot = (gux * dx + guy * dy + guz * dz) * di * di * di;
                        gdx -= dx * dot;
                        gdy -= dy * dot;
                        gdz -= dz * dot;
                    }
                    gpx += gdx;
                    gpy += gdy;
                    gpz += gdz;
                    if (p->want_vm) {
                        double *gv = gvm + c * 15;
                        gv[12] -= gdx;
                        gv[13] -= gdy;
                        gv[14] -= gdz;
                    }
                }
            }
            p->g_means[3 * n] = (float)gpx, p->g_means[3 * n + 1] = (float)gpy, p->g_means[3 * n + 2] = (float)gpz;
            double gM[9];
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) {
                    double acc = 0.0;
                    for (int k = 0; k < 3; k++) acc += (gS[i * 3 + k] + gS[k * 3 + i]) * m9[k * 3 + j];
                    gM[i * 3 + j] = acc;
                }
            double gsx = gM[0] * r9[0] + gM[3] * r9[3] + gM[6] * r9[6];
            double gsy = gM[1] * r9[1] + gM[4] * r9[4] + gM[7] * r9[7];
            double gsz = gM[2] * r9[2] + gM[5] * r9[5] + gM[8] * r9[8];
            p->g_scales[3 * n] = (float)gsx, p->g_scales[3 * n + 1] = (float)gsy, p->g_scales[3 * n + 2] = (float)gsz;
            double G[9];
            for (int i = 0; i < 3; i++) {
                G[i * 3] = gM[i * 3] * g.sx;
                G[i * 3 + 1] = gM[i * 3 + 1] * g.sy;
                G[i * 3 + 2] = gM[i * 3 + 2] * g.sz;
            }
            double w = g.qw * g.inv, a = g.qx * g.inv, b = g.qy * g.inv, d = g.qz * g.inv;
            double gw = 2.0 * (-G[1] * d + G[2] * b + G[3] * d - G[5] * a - G[6] * b + G[7] * a);
            double ga_ = 2.0 * (G[1] * b + G[2] * d + G[3] * b - 2.0 * G[4] * a - G[5] * w + G[6] * d + G[7] * w
                                - 2.0 * G[8] * a);
            double gb_ = 2.0 * (-2.0 * G[0] * b + G[1] * a + G[2] * w + G[3] * a + G[5] * d - G[6] * w + G[7] * d
                                - 2.0 * G[8] * b);
            double gd = 2.0 * (-2.0 * G[0] * d - G[1] * w + G[2] * a + G[3] * w - 2.0 * G[4] * d + G[5] * b
                               + G[6] * a + G[7] * b);
            double dot = 0.0;
            if (g.sq >= 1e-24) dot = (gw * g.qw + ga_ * g.qx + gb_ * g.qy + gd * g.qz) * g.inv * g.inv * g.inv;
            p->g_quats[4 * n] = (float)(gw * g.inv - g.qw * dot);
            p->g_quats[4 * n + 1] = (float)(ga_ * g.inv - g.qx * dot);
            p->g_quats[4 * n + 2] = (float)(gb_ * g.inv - g.qy * dot);
            p->g_quats[4 * n + 3] = (float)(gd * g.inv - g.qz * dot);
            if (deg >= 0) {
                float *o = p->g_sh + n * KS * 3;
                for (int64_t k = 0; k < KS * 3; k++) o[k] = k < K * 3 ? (float)gsh[k] : 0.0f;
            }
        }
    }
}

/* the 4-lane forward (the projection body at the end of this file), built for AVX2 and the baseline */
#undef RASTER_BODY
#define PROJ_BODY 1
#if X86
#define SUF(name) name##_avx2
#define HAVE_AVX 1
#define TARGET __attribute__((target("avx2")))
#include "_raster.c"
#undef SUF
#undef HAVE_AVX
#undef TARGET
#endif
#define SUF(name) name##_portable
#define HAVE_AVX 0
#define TARGET
#include "_raster.c"
#undef SUF
#undef HAVE_AVX
#undef TARGET
#undef PROJ_BODY

/* the items split into contiguous ranges, one per thread, each starting at a multiple of `unit`: with unit 4
   every Gaussian lands in the same group of 4 lanes (and the scalar tail is the last group's) for any thread
   count, so the results do not depend on it */
static void split_run(const proj_t *p, int64_t n_items, int64_t unit, void *(*fn)(void *))
{
    int64_t n_units = (n_items + unit - 1) / unit;
    int64_t n_threads = p->n_threads < 1 ? 1 : (p->n_threads > MAX_THREADS ? MAX_THREADS : p->n_threads);
    if (n_threads > n_units) n_threads = n_units > 0 ? n_units : 1;
    prange_t parts[MAX_THREADS];
    pthread_t tid[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int64_t t = 0; t < n_threads; t++) {
        int64_t lo = unit * (n_units * t / n_threads), hi = unit * (n_units * (t + 1) / n_threads);
        parts[t] = (prange_t){p, lo < n_items ? lo : n_items, hi < n_items ? hi : n_items};
    }
    for (int64_t t = 1; t < n_threads; t++) started[t] = pthread_create(&tid[t], NULL, fn, &parts[t]) == 0;
    fn(&parts[0]);
    for (int64_t t = 1; t < n_threads; t++) {
        if (started[t]) pthread_join(tid[t], NULL);
        else fn(&parts[t]);
    }
}

/* project_cpu._project_forward / _project_backward (float32 inputs; see proj_t). The backward's g_vm
   (blocks, C, 15) must be zeroed by the caller (it is added to, as the numba kernel's). */
void ev3dgs_project_forward(const proj_t *p)
{
#if X86
    if (ev3dgs_raster_isa(p->isa)) {
        split_run(p, p->N, 4, project_forward_range4_avx2);
        return;
    }
#endif
    split_run(p, p->N, 4, project_forward_range4_portable);
}

void ev3dgs_project_backward(const proj_t *p)
{
    int64_t blocks = (p->N + VM_BLOCK - 1) / VM_BLOCK;
#if X86
    if (ev3dgs_raster_isa(p->isa)) {
        split_run(p, blocks, 1, project_backward_range4_avx2);
        return;
    }
#endif
    split_run(p, blocks, 1, project_backward_range4_portable);
}

static PyMethodDef methods[] = {{NULL, NULL, 0, NULL}};
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "ev3dgs.splat._raster",
                                    "The cpu backend's SIMD tile kernels (called through ctypes: see "
                                    "ev3dgs.splat.cpu_simd).", -1, methods, NULL, NULL, NULL, NULL};
PyMODINIT_FUNC PyInit__raster(void) { return PyModule_Create(&module); }

#elif defined(RASTER_BODY) /* ------------------------------------------- kernel body, built twice -- */

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
    if (job->write_rows)  /* every row written (no zeroed buffer): the entries after every pixel's last, 0 */
        memset(job->per_pair + kmax * (6 + D), 0, sizeof(float) * (size_t)((end - kmax) * (6 + D)));
    for (int64_t k = kmax - 1; k >= start; k--) {
        if (job->record && job->frag_n[k] == 0) {  /* per_pair[k] stays 0 (or is written 0) */
            if (job->write_rows) memset(job->per_pair + k * (6 + D), 0, sizeof(float) * (size_t)(6 + D));
            continue;
        }
        float *pp = job->per_pair + k * (6 + D);
        const float *q = job->params + k * stride;
        const int32_t *bx = job->boxes + 4 * k;
        int32_t bx0 = bx[0], bx1 = bx[1], by0 = bx[2], by1 = bx[3];
        if (bx0 > bx1 || by0 > by1) {
            if (job->write_rows) memset(pp, 0, sizeof(float) * (size_t)(6 + D));
            continue;
        }
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
        if (job->write_rows) {  /* not zeroed before: 0 + x, the same values as += on a zeroed row */
            pp[0] = 0.0f + SUF(hsum)(gmx);
            pp[1] = 0.0f + SUF(hsum)(gmy);
            pp[2] = 0.0f + SUF(hsum)(ga);
            pp[3] = 0.0f + SUF(hsum)(gb);
            pp[4] = 0.0f + SUF(hsum)(gc);
            pp[5] = 0.0f + SUF(hsum)(go);
        } else {
            pp[0] += SUF(hsum)(gmx);
            pp[1] += SUF(hsum)(gmy);
            pp[2] += SUF(hsum)(ga);
            pp[3] += SUF(hsum)(gb);
            pp[4] += SUF(hsum)(gc);
            pp[5] += SUF(hsum)(go);
        }
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

#else /* ------------------------------------------------- projection body, built twice -- */

/* ---- projection + SH forward, 4 Gaussians per vector (float64 lanes): the scalar code's operations lane by
   lane (IEEE operations are the same in a lane as in a scalar register; branches become selects of the
   value the scalar code would keep), so bitwise its results (tested) ---- */
typedef double v4d __attribute__((vector_size(32)));
typedef int64_t v4l __attribute__((vector_size(32)));

static inline TARGET v4d SUF(dbc)(double x) { return (v4d){x, x, x, x}; }
static inline TARGET v4d SUF(dsel)(v4l m, v4d a, v4d b) { return (v4d)((m & (v4l)a) | (~m & (v4l)b)); }
static inline TARGET v4d SUF(dmax)(v4d a, v4d b) { return SUF(dsel)(b > a, b, a); }  /* Python's max(a, b) */
static inline TARGET v4d SUF(dmin)(v4d a, v4d b) { return SUF(dsel)(b < a, b, a); }
static inline TARGET v4d SUF(dsqrt)(v4d x)
{
#if HAVE_AVX
    return __builtin_ia32_sqrtpd256(x);
#else
    return (v4d){sqrt(x[0]), sqrt(x[1]), sqrt(x[2]), sqrt(x[3])};
#endif
}

/* the SH basis up to degree deg (at most 3) at the unit directions (ux, uy, uz), the scalar kernels' operations */
static TARGET inline void SUF(sh_basis4)(int64_t deg, v4d ux, v4d uy, v4d uz, v4d *basis)
{
    v4d two = SUF(dbc)(2.0);
    basis[0] = SUF(dbc)(SH_C0);
    if (deg >= 1) {
        basis[1] = SUF(dbc)(-SH_C1) * uy;
        basis[2] = SUF(dbc)(SH_C1) * uz;
        basis[3] = SUF(dbc)(-SH_C1) * ux;
    }
    if (deg >= 2) {
        v4d xx = ux * ux, yy = uy * uy, zz = uz * uz, xy = ux * uy, yz2 = uy * uz, xz2 = ux * uz;
        v4d three = SUF(dbc)(3.0), four = SUF(dbc)(4.0);
        basis[4] = SUF(dbc)(SH_C2[0]) * xy;
        basis[5] = SUF(dbc)(SH_C2[1]) * yz2;
        basis[6] = SUF(dbc)(SH_C2[2]) * (two * zz - xx - yy);
        basis[7] = SUF(dbc)(SH_C2[3]) * xz2;
        basis[8] = SUF(dbc)(SH_C2[4]) * (xx - yy);
        if (deg >= 3) {
            basis[9] = SUF(dbc)(SH_C3[0]) * uy * (three * xx - yy);
            basis[10] = SUF(dbc)(SH_C3[1]) * xy * uz;
            basis[11] = SUF(dbc)(SH_C3[2]) * uy * (four * zz - xx - yy);
            basis[12] = SUF(dbc)(SH_C3[3]) * uz * (two * zz - three * xx - three * yy);
            basis[13] = SUF(dbc)(SH_C3[4]) * ux * (four * zz - xx - yy);
            basis[14] = SUF(dbc)(SH_C3[5]) * uz * (xx - yy);
            basis[15] = SUF(dbc)(SH_C3[6]) * ux * (xx - three * yy);
        }
    }
}

/* the screen-space covariance of 4 Gaussians in one camera (world-to-camera rows v, 3D covariance S, the
   projection's Jacobian entries j00, j02, j11, j12): T = J W (rows t0, t1) and C2 = T S T^T + eps2d I, the
   scalar kernels' operations */
static TARGET inline void SUF(cov2d4)(const v4d *S, const double *v, v4d j00, v4d j02, v4d j11, v4d j12,
                                      double eps2d, v4d *t0, v4d *t1, v4d *c11, v4d *c12, v4d *c22)
{
    t0[0] = j00 * SUF(dbc)(v[0]) + j02 * SUF(dbc)(v[8]), t0[1] = j00 * SUF(dbc)(v[1]) + j02 * SUF(dbc)(v[9]);
    t0[2] = j00 * SUF(dbc)(v[2]) + j02 * SUF(dbc)(v[10]);
    t1[0] = j11 * SUF(dbc)(v[4]) + j12 * SUF(dbc)(v[8]), t1[1] = j11 * SUF(dbc)(v[5]) + j12 * SUF(dbc)(v[9]);
    t1[2] = j11 * SUF(dbc)(v[6]) + j12 * SUF(dbc)(v[10]);
    v4d u0 = S[0] * t0[0] + S[1] * t0[1] + S[2] * t0[2];
    v4d u1 = S[3] * t0[0] + S[4] * t0[1] + S[5] * t0[2];
    v4d u2 = S[6] * t0[0] + S[7] * t0[1] + S[8] * t0[2];
    v4d v0 = S[0] * t1[0] + S[1] * t1[1] + S[2] * t1[2];
    v4d v1 = S[3] * t1[0] + S[4] * t1[1] + S[5] * t1[2];
    v4d v2 = S[6] * t1[0] + S[7] * t1[1] + S[8] * t1[2];
    v4d eps = SUF(dbc)(eps2d);
    *c11 = t0[0] * u0 + t0[1] * u1 + t0[2] * u2 + eps;
    *c12 = t0[0] * v0 + t0[1] * v1 + t0[2] * v2;
    *c22 = t1[0] * v0 + t1[1] * v1 + t1[2] * v2 + eps;
}

/* 4 Gaussians n ... n + 3 loaded (a non-finite row's lane: zero mean, unit quaternion and scales) with what
   both projection passes derive from them, in the scalar kernels' operations: the normalised quaternion, the
   rotation R, M = R diag(s) and the 3D covariance S = M M^T */
typedef struct {
    v4l fin;
    v4d px, py, pz, qw, qx, qy, qz, sx, sy, sz, sq, inv, w_, x_, y_, z_, r[9], m[9], S[9];
} SUF(gauss4_t);

static TARGET inline void SUF(gauss4)(const proj_t *p, int64_t n, SUF(gauss4_t) *G)
{
    v4d px, py, pz, qw, qx, qy, qz, sx, sy, sz;
    v4l fin;
    for (int i = 0; i < 4; i++) {
        int64_t g = n + i;
        fin[i] = finite_row(p, g) ? -1 : 0;
        px[i] = p->means[3 * g], py[i] = p->means[3 * g + 1], pz[i] = p->means[3 * g + 2];
        qw[i] = p->quats[4 * g], qx[i] = p->quats[4 * g + 1], qy[i] = p->quats[4 * g + 2], qz[i] = p->quats[4 * g + 3];
        sx[i] = p->scales[3 * g], sy[i] = p->scales[3 * g + 1], sz[i] = p->scales[3 * g + 2];
    }
    v4d zero = SUF(dbc)(0.0), one = SUF(dbc)(1.0), two = SUF(dbc)(2.0);
    px = SUF(dsel)(fin, px, zero), py = SUF(dsel)(fin, py, zero), pz = SUF(dsel)(fin, pz, zero);
    qw = SUF(dsel)(fin, qw, one), qx = SUF(dsel)(fin, qx, one), qy = SUF(dsel)(fin, qy, one);
    qz = SUF(dsel)(fin, qz, one);
    sx = SUF(dsel)(fin, sx, one), sy = SUF(dsel)(fin, sy, one), sz = SUF(dsel)(fin, sz, one);
    v4d sq = qw * qw + qx * qx + qy * qy + qz * qz;
    v4d inv = one / SUF(dsqrt)(SUF(dmax)(sq, SUF(dbc)(1e-24)));
    v4d w_ = qw * inv, x_ = qx * inv, y_ = qy * inv, z_ = qz * inv;
    v4d r[9] = {one - two * (y_ * y_ + z_ * z_), two * (x_ * y_ - w_ * z_), two * (x_ * z_ + w_ * y_),
                two * (x_ * y_ + w_ * z_), one - two * (x_ * x_ + z_ * z_), two * (y_ * z_ - w_ * x_),
                two * (x_ * z_ - w_ * y_), two * (y_ * z_ + w_ * x_), one - two * (x_ * x_ + y_ * y_)};
    v4d m[9] = {r[0] * sx, r[1] * sy, r[2] * sz, r[3] * sx, r[4] * sy, r[5] * sz, r[6] * sx, r[7] * sy, r[8] * sz};
    v4d s00 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
    v4d s01 = m[0] * m[3] + m[1] * m[4] + m[2] * m[5];
    v4d s02 = m[0] * m[6] + m[1] * m[7] + m[2] * m[8];
    v4d s11 = m[3] * m[3] + m[4] * m[4] + m[5] * m[5];
    v4d s12 = m[3] * m[6] + m[4] * m[7] + m[5] * m[8];
    v4d s22 = m[6] * m[6] + m[7] * m[7] + m[8] * m[8];
    v4d S[9] = {s00, s01, s02, s01, s11, s12, s02, s12, s22};
    *G = (SUF(gauss4_t)){fin, px, py, pz, qw, qx, qy, qz, sx, sy, sz, sq, inv, w_, x_, y_, z_,
                         {r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]},
                         {m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]},
                         {S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7], S[8]}};
}

static TARGET void SUF(project_forward4)(const proj_t *p, int64_t n)
{
    int64_t N = p->N, C = p->C, deg = p->deg, K = (deg + 1) * (deg + 1), KS = p->KS;
    SUF(gauss4_t) g4;
    SUF(gauss4)(p, n, &g4);
    v4l fin = g4.fin;
    v4d px = g4.px, py = g4.py, pz = g4.pz, *S = g4.S;
    v4d o, lg;
    for (int i = 0; i < 4; i++) {
        o[i] = fin[i] ? (double)p->opac[n + i] : 1.0;
        lg[i] = log(255.0 * o[i]);
    }
    v4d zero = SUF(dbc)(0.0), one = SUF(dbc)(1.0), two = SUF(dbc)(2.0);
    v4d extent = SUF(dsqrt)(two * SUF(dmax)(lg, zero));
    v4l bright = ~(o < SUF(dbc)(p->alpha_min));
    for (int64_t c = 0; c < C; c++) {
        const double *v = p->vm + 16 * c, *cam = p->cam + 8 * c;
        double fx = cam[0], fy = cam[1];
        v4d x = SUF(dbc)(v[0]) * px + SUF(dbc)(v[1]) * py + SUF(dbc)(v[2]) * pz + SUF(dbc)(v[3]);
        v4d y = SUF(dbc)(v[4]) * px + SUF(dbc)(v[5]) * py + SUF(dbc)(v[6]) * pz + SUF(dbc)(v[7]);
        v4d zr = SUF(dbc)(v[8]) * px + SUF(dbc)(v[9]) * py + SUF(dbc)(v[10]) * pz + SUF(dbc)(v[11]);
        v4l valid = (zr > SUF(dbc)(p->near_)) & (zr < SUF(dbc)(p->far_)) & fin;
        v4d z = SUF(dsel)(valid, zr, one);
        v4d xz = x / z, yz = y / z;
        v4d cxz = SUF(dmin)(SUF(dmax)(xz, SUF(dbc)(-cam[4])), SUF(dbc)(cam[5]));
        v4d cyz = SUF(dmin)(SUF(dmax)(yz, SUF(dbc)(-cam[6])), SUF(dbc)(cam[7]));
        v4d tx = z * cxz, ty = z * cyz;
        v4d rz = one / z;
        v4d vfx = SUF(dbc)(fx), vfy = SUF(dbc)(fy);
        v4d j00 = vfx * rz, j02 = -vfx * tx * rz * rz, j11 = vfy * rz, j12 = -vfy * ty * rz * rz;
        v4d t0[3], t1[3], c11, c12, c22;
        SUF(cov2d4)(S, v, j00, j02, j11, j12, p->eps2d, t0, t1, &c11, &c12, &c22);
        v4d det = SUF(dmax)(c11 * c22 - c12 * c12, SUF(dbc)(1e-12));
        v4d ca = c22 / det, cb = -c12 / det, cc = c11 / det;
        v4d mx = vfx * xz + SUF(dbc)(cam[2]), my = vfy * yz + SUF(dbc)(cam[3]);
        v4d mid = SUF(dbc)(0.5) * (c11 + c22);
        v4d lam = mid + SUF(dsqrt)(SUF(dmax)(mid * mid - (c11 * c22 - c12 * c12), SUF(dbc)(0.1)));
        v4d rr = extent * SUF(dsqrt)(SUF(dmax)(lam, zero)) * SUF(dbc)(1.0 + p->radius_margin);
        v4d colv[3];
        if (deg >= 0) {
            const double *cpos = p->campos + 3 * c;
            v4d dx = px - SUF(dbc)(cpos[0]), dy = py - SUF(dbc)(cpos[1]), dz = pz - SUF(dbc)(cpos[2]);
            v4d d2 = SUF(dmax)(dx * dx + dy * dy + dz * dz, SUF(dbc)(1e-24));
            v4d di = one / SUF(dsqrt)(d2);
            v4d ux = dx * di, uy = dy * di, uz = dz * di;
            v4d basis[16];
            SUF(sh_basis4)(deg, ux, uy, uz, basis);
            for (int ch = 0; ch < 3; ch++) {
                v4d acc = zero;
                for (int64_t k = 0; k < K; k++) {
                    v4d shv;
                    for (int i = 0; i < 4; i++) shv[i] = p->sh[((n + i) * KS + k) * 3 + ch];
                    acc += basis[k] * shv;
                }
                colv[ch] = SUF(dmax)(acc + SUF(dbc)(0.5), zero);
            }
        }
        for (int i = 0; i < 4; i++) {
            int64_t cn = c * N + n + i;
            p->conics[3 * cn] = (float)ca[i];
            p->conics[3 * cn + 1] = (float)cb[i];
            p->conics[3 * cn + 2] = (float)cc[i];
            p->means2d[2 * cn] = (float)mx[i];
            p->means2d[2 * cn + 1] = (float)my[i];
            p->depths[cn] = (float)zr[i];
            double rad = 0.0;
            if (valid[i] && fin[i] && bright[i]) {
                rad = ceil_as_int(rr[i]);
                if (!finite_d(rad)) rad = 0.0;
                else if (rad < 1.0) rad = 1.0;
                if (mx[i] + rad < -0.5 || mx[i] - rad > p->width - 0.5 || my[i] + rad < -0.5
                    || my[i] - rad > p->height - 0.5 || !finite_d(mx[i]) || !finite_d(my[i]))
                    rad = 0.0;
            }
            p->radii[cn] = (int32_t)(int64_t)pmin(rad, 1073741824.0);
            if (deg >= 0)
                for (int ch = 0; ch < 3; ch++) p->colors[3 * cn + ch] = (float)colv[ch][i];
        }
    }
}

static TARGET void *SUF(project_forward_range4)(void *arg)
{
    const prange_t *rg = arg;
    int64_t n = rg->lo;
    for (; n + 4 <= rg->hi; n += 4) SUF(project_forward4)(rg->p, n);
    if (n < rg->hi) {
        prange_t rest = {rg->p, n, rg->hi};
        project_forward_range(&rest);
    }
    return NULL;
}


/* the backward for 4 Gaussians n ... n + 3 of one block (blocks hold a multiple of 4), lane by lane the scalar
   backward's operations; a non-finite lane gets zero gradients and adds nothing to the camera sums, whose
   additions stay in Gaussian order (lane 0, 1, 2, 3 in turn) */
static TARGET void SUF(project_backward4)(const proj_t *p, int64_t n, double *gvm)
{
    int64_t N = p->N, C = p->C, deg = p->deg, K = (deg + 1) * (deg + 1), KS = p->KS;
    SUF(gauss4_t) g4;
    SUF(gauss4)(p, n, &g4);
    v4l fin = g4.fin;
    v4d px = g4.px, py = g4.py, pz = g4.pz, qw = g4.qw, qx = g4.qx, qy = g4.qy, qz = g4.qz;
    v4d sx = g4.sx, sy = g4.sy, sz = g4.sz, sq = g4.sq, inv = g4.inv, w_ = g4.w_, x_ = g4.x_, y_ = g4.y_;
    v4d z_ = g4.z_, *r = g4.r, *m = g4.m, *S = g4.S;
    v4d zero = SUF(dbc)(0.0), one = SUF(dbc)(1.0), two = SUF(dbc)(2.0), half = SUF(dbc)(0.5);
    v4d gpx = zero, gpy = zero, gpz = zero, gS[9], gsh[48];
    for (int i = 0; i < 9; i++) gS[i] = zero;
    for (int i = 0; i < 48; i++) gsh[i] = zero;
    for (int64_t c = 0; c < C; c++) {
        const double *vm = p->vm + 16 * c, *cam = p->cam + 8 * c;
        v4d V[12];
        for (int i = 0; i < 12; i++) V[i] = SUF(dbc)(vm[i]);
        v4d vfx = SUF(dbc)(cam[0]), vfy = SUF(dbc)(cam[1]);
        v4d x = V[0] * px + V[1] * py + V[2] * pz + V[3];
        v4d y = V[4] * px + V[5] * py + V[6] * pz + V[7];
        v4d zr = V[8] * px + V[9] * py + V[10] * pz + V[11];
        v4l valid = (zr > SUF(dbc)(p->near_)) & (zr < SUF(dbc)(p->far_)) & fin;
        v4d z = SUF(dsel)(valid, zr, one);
        v4d xz = x / z, yz = y / z;
        v4d cxz = SUF(dmin)(SUF(dmax)(xz, SUF(dbc)(-cam[4])), SUF(dbc)(cam[5]));
        v4d cyz = SUF(dmin)(SUF(dmax)(yz, SUF(dbc)(-cam[6])), SUF(dbc)(cam[7]));
        v4d tx = z * cxz, ty = z * cyz;
        v4d rz = one / z;
        v4d j00 = vfx * rz, j02 = -vfx * tx * rz * rz, j11 = vfy * rz, j12 = -vfy * ty * rz * rz;
        v4d t0[3], t1[3], c11, c12, c22;
        SUF(cov2d4)(S, vm, j00, j02, j11, j12, p->eps2d, t0, t1, &c11, &c12, &c22);
        v4d det_raw = c11 * c22 - c12 * c12;
        v4d det = SUF(dmax)(det_raw, SUF(dbc)(1e-12));
        v4d ga, gbb, gc, gm0, gm1, gdep;
        for (int i = 0; i < 4; i++) {
            int64_t cn = c * N + n + i;
            ga[i] = p->g_con[3 * cn], gbb[i] = p->g_con[3 * cn + 1], gc[i] = p->g_con[3 * cn + 2];
            gm0[i] = p->g_m2d[2 * cn], gm1[i] = p->g_m2d[2 * cn + 1], gdep[i] = p->g_dep[cn];
        }
        v4d g11 = gc / det, g12 = -gbb / det, g22 = ga / det;
        {
            v4l big = det_raw >= SUF(dbc)(1e-12);
            v4d gdet = -(ga * c22 - gbb * c12 + gc * c11) / (det * det);
            g11 = SUF(dsel)(big, g11 + gdet * c22, g11);
            g22 = SUF(dsel)(big, g22 + gdet * c11, g22);
            g12 = SUF(dsel)(big, g12 - two * gdet * c12, g12);
        }
        v4d h = half * g12;
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                gS[i * 3 + j] += (g11 * t0[i] * t0[j] + h * (t0[i] * t1[j] + t1[i] * t0[j]) + g22 * t1[i] * t1[j]);
        v4d u[3], v[3];
        for (int i = 0; i < 3; i++) {
            u[i] = S[i * 3] * t0[0] + S[i * 3 + 1] * t0[1] + S[i * 3 + 2] * t0[2];
            v[i] = S[i * 3] * t1[0] + S[i * 3 + 1] * t1[1] + S[i * 3 + 2] * t1[2];
        }
        v4d gT0[3] = {two * (g11 * u[0] + h * v[0]), two * (g11 * u[1] + h * v[1]), two * (g11 * u[2] + h * v[2])};
        v4d gT1[3] = {two * (h * u[0] + g22 * v[0]), two * (h * u[1] + g22 * v[1]), two * (h * u[2] + g22 * v[2])};
        v4d gj00 = gT0[0] * V[0] + gT0[1] * V[1] + gT0[2] * V[2];
        v4d gj02 = gT0[0] * V[8] + gT0[1] * V[9] + gT0[2] * V[10];
        v4d gj11 = gT1[0] * V[4] + gT1[1] * V[5] + gT1[2] * V[6];
        v4d gj12 = gT1[0] * V[8] + gT1[1] * V[9] + gT1[2] * V[10];
        v4d grz = vfx * gj00 + vfy * gj11 - two * vfx * tx * rz * gj02 - two * vfy * ty * rz * gj12;
        v4d gtx = -vfx * rz * rz * gj02;
        v4d gty = -vfy * rz * rz * gj12;
        v4d gz = -grz * rz * rz + gtx * cxz + gty * cyz;
        v4d gxz = vfx * gm0, gyz = vfy * gm1;
        gxz = SUF(dsel)((xz > SUF(dbc)(-cam[4])) & (xz < SUF(dbc)(cam[5])), gxz + gtx * z, gxz);
        gyz = SUF(dsel)((yz > SUF(dbc)(-cam[6])) & (yz < SUF(dbc)(cam[7])), gyz + gty * z, gyz);
        v4d gx = gxz / z, gy = gyz / z;
        gz -= (gxz * x + gyz * y) / (z * z);
        v4d gzr = gdep + SUF(dsel)(valid, gz, zero);
        gpx += V[0] * gx + V[4] * gy + V[8] * gzr;
        gpy += V[1] * gx + V[5] * gy + V[9] * gzr;
        gpz += V[2] * gx + V[6] * gy + V[10] * gzr;
        v4d cvm[15];
        if (p->want_vm) {
            v4d pj[3] = {px, py, pz};
            for (int j = 0; j < 3; j++) {
                cvm[j] = gx * pj[j] + j00 * gT0[j];
                cvm[4 + j] = gy * pj[j] + j11 * gT1[j];
                cvm[8 + j] = gzr * pj[j] + j02 * gT0[j] + j12 * gT1[j];
            }
            cvm[3] = gx, cvm[7] = gy, cvm[11] = gzr;
        }
        if (deg >= 0) {
            const double *cpos = p->campos + 3 * c;
            v4d dx = px - SUF(dbc)(cpos[0]), dy = py - SUF(dbc)(cpos[1]), dz = pz - SUF(dbc)(cpos[2]);
            v4d d2r = dx * dx + dy * dy + dz * dz;
            v4d d2 = SUF(dmax)(d2r, SUF(dbc)(1e-24));
            v4d di = one / SUF(dsqrt)(d2);
            v4d ux = dx * di, uy = dy * di, uz = dz * di;
            v4d basis[16], gb[16];
            v4d three = SUF(dbc)(3.0), four = SUF(dbc)(4.0), six = SUF(dbc)(6.0), eight = SUF(dbc)(8.0);
            SUF(sh_basis4)(deg, ux, uy, uz, basis);
            v4d xx = ux * ux, yy = uy * uy, zz = uz * uz;
            for (int64_t k = 0; k < K; k++) gb[k] = zero;
            for (int ch = 0; ch < 3; ch++) {
                v4d shv[16], gcol;
                v4d acc = zero;
                for (int64_t k = 0; k < K; k++) {
                    for (int i = 0; i < 4; i++) shv[k][i] = p->sh[((n + i) * KS + k) * 3 + ch];
                    acc += basis[k] * shv[k];
                }
                for (int i = 0; i < 4; i++) gcol[i] = p->g_col[3 * (c * N + n + i) + ch];
                v4l on = acc + half >= zero;
                for (int64_t k = 0; k < K; k++) {
                    gsh[k * 3 + ch] = SUF(dsel)(on, gsh[k * 3 + ch] + basis[k] * gcol, gsh[k * 3 + ch]);
                    gb[k] = SUF(dsel)(on, gb[k] + shv[k] * gcol, gb[k]);
                }
            }
            v4d gux = zero, guy = zero, guz = zero, g;
            if (deg >= 1) {
                guy -= SUF(dbc)(SH_C1) * gb[1];
                guz += SUF(dbc)(SH_C1) * gb[2];
                gux -= SUF(dbc)(SH_C1) * gb[3];
            }
            if (deg >= 2) {
                g = SUF(dbc)(SH_C2[0]) * gb[4]; gux += g * uy; guy += g * ux;
                g = SUF(dbc)(SH_C2[1]) * gb[5]; guy += g * uz; guz += g * uy;
                g = SUF(dbc)(SH_C2[2]) * gb[6]; gux -= two * g * ux; guy -= two * g * uy; guz += four * g * uz;
                g = SUF(dbc)(SH_C2[3]) * gb[7]; gux += g * uz; guz += g * ux;
                g = SUF(dbc)(SH_C2[4]) * gb[8]; gux += two * g * ux; guy -= two * g * uy;
                if (deg >= 3) {
                    g = SUF(dbc)(SH_C3[0]) * gb[9]; gux += g * six * ux * uy; guy += g * (three * xx - three * yy);
                    g = SUF(dbc)(SH_C3[1]) * gb[10]; gux += g * uy * uz; guy += g * ux * uz; guz += g * ux * uy;
                    g = SUF(dbc)(SH_C3[2]) * gb[11]; gux -= g * two * ux * uy;
                    guy += g * (four * zz - xx - three * yy); guz += g * eight * uy * uz;
                    g = SUF(dbc)(SH_C3[3]) * gb[12]; gux -= g * six * ux * uz; guy -= g * six * uy * uz;
                    guz += g * (six * zz - three * xx - three * yy);
                    g = SUF(dbc)(SH_C3[4]) * gb[13]; gux += g * (four * zz - three * xx - yy);
                    guy -= g * two * ux * uy; guz += g * eight * ux * uz;
                    g = SUF(dbc)(SH_C3[5]) * gb[14]; gux += g * two * ux * uz; guy -= g * two * uy * uz;
                    guz += g * (xx - yy);
                    g = SUF(dbc)(SH_C3[6]) * gb[15]; gux += g * (three * xx - three * yy); guy -= g * six * ux * uy;
                }
            }
            v4d gdx = gux * di, gdy = guy * di, gdz = guz * di;
            {
                v4l ok = d2r >= SUF(dbc)(1e-24);
                v4d dot = (gux * dx + guy * dy + guz * dz) * di * di * di;
                gdx = SUF(dsel)(ok, gdx - dx * dot, gdx);
                gdy = SUF(dsel)(ok, gdy - dy * dot, gdy);
                gdz = SUF(dsel)(ok, gdz - dz * dot, gdz);
            }
            gpx += gdx;
            gpy += gdy;
            gpz += gdz;
            if (p->want_vm) cvm[12] = gdx, cvm[13] = gdy, cvm[14] = gdz;
        }
        if (p->want_vm) {
            double *gv = gvm + c * 15;
            for (int i = 0; i < 4; i++) {
                if (!fin[i]) continue;
                for (int j = 0; j < 12; j++) gv[j] += cvm[j][i];
                if (deg >= 0)
                    for (int j = 12; j < 15; j++) gv[j] -= cvm[j][i];
            }
        }
    }
    v4d gM[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            v4d acc = zero;
            for (int k = 0; k < 3; k++) acc += (gS[i * 3 + k] + gS[k * 3 + i]) * m[k * 3 + j];
            gM[i * 3 + j] = acc;
        }
    v4d gsx = gM[0] * r[0] + gM[3] * r[3] + gM[6] * r[6];
    v4d gsy = gM[1] * r[1] + gM[4] * r[4] + gM[7] * r[7];
    v4d gsz = gM[2] * r[2] + gM[5] * r[5] + gM[8] * r[8];
    v4d G[9];
    for (int i = 0; i < 3; i++) {
        G[i * 3] = gM[i * 3] * sx;
        G[i * 3 + 1] = gM[i * 3 + 1] * sy;
        G[i * 3 + 2] = gM[i * 3 + 2] * sz;
    }
    v4d w = w_, a = x_, b = y_, d = z_;
    v4d gw = two * (-G[1] * d + G[2] * b + G[3] * d - G[5] * a - G[6] * b + G[7] * a);
    v4d ga_ = two * (G[1] * b + G[2] * d + G[3] * b - two * G[4] * a - G[5] * w + G[6] * d + G[7] * w
                     - two * G[8] * a);
    v4d gb_ = two * (-two * G[0] * b + G[1] * a + G[2] * w + G[3] * a + G[5] * d - G[6] * w + G[7] * d
                     - two * G[8] * b);
    v4d gd = two * (-two * G[0] * d - G[1] * w + G[2] * a + G[3] * w - two * G[4] * d + G[5] * b + G[6] * a
                    + G[7] * b);
    v4d dot = SUF(dsel)(sq >= SUF(dbc)(1e-24), (gw * qw + ga_ * qx + gb_ * qy + gd * qz) * inv * inv * inv, zero);
    v4d oq[4] = {gw * inv - qw * dot, ga_ * inv - qx * dot, gb_ * inv - qy * dot, gd * inv - qz * dot};
    for (int i = 0; i < 4; i++) {
        int64_t g = n + i;
        int f = fin[i] != 0;
        p->g_means[3 * g] = f ? (float)gpx[i] : 0.0f;
        p->g_means[3 * g + 1] = f ? (float)gpy[i] : 0.0f;
        p->g_means[3 * g + 2] = f ? (float)gpz[i] : 0.0f;
        p->g_scales[3 * g] = f ? (float)gsx[i] : 0.0f;
        p->g_scales[3 * g + 1] = f ? (float)gsy[i] : 0.0f;
        p->g_scales[3 * g + 2] = f ? (float)gsz[i] : 0.0f;
        for (int j = 0; j < 4; j++) p->g_quats[4 * g + j] = f ? (float)oq[j][i] : 0.0f;
        if (deg >= 0) {
            float *o = p->g_sh + g * KS * 3;
            for (int64_t k = 0; k < KS * 3; k++) o[k] = f && k < K * 3 ? (float)gsh[k][i] : 0.0f;
        }
    }
}

static TARGET void *SUF(project_backward_range4)(void *arg)
{
    const prange_t *rg = arg;   /* blocks */
    const proj_t *p = rg->p;
    for (int64_t blk = rg->lo; blk < rg->hi; blk++) {
        int64_t n = blk * VM_BLOCK, n1 = (blk + 1) * VM_BLOCK < p->N ? (blk + 1) * VM_BLOCK : p->N;
        for (; n + 4 <= n1; n += 4) SUF(project_backward4)(p, n, p->g_vm + blk * p->C * 15);
        if (n < n1) project_backward_gaussians(p, blk, n, n1);  /* the last block's tail, scalar */
    }
    return NULL;
}

#endif
