/* AEDAT 4.0 events packets: read, decompress, parse and unpack in one pass per packet, without the GIL.
 *
 * The fast path of ev3dgs.io.aedat4_fast (which documents the contract). For each packet of a FileDataTable-
 * indexed events stream it reads the packet (pread), checks its header against the table, decompresses it
 * with the LZ4 frame / zstd library function whose address the caller passes (the same functions
 * aedat4_codec calls through ctypes), parses the size-prefixed EVTS flatbuffer with every position checked,
 * and unpacks the 16-byte Event structs into t (int64), x, y (uint16), p (int8 +1/-1) while gathering what
 * the per-packet checks need. A packet is committed only when it is intact by every check the general path
 * makes (element count = the table's, coordinates inside the sensor, polarity bytes 0/1, time order inside
 * the packet and after the previous packet, inside the table's time range); at the first packet that is not,
 * the call stops and returns its index: the caller decodes that one packet through the general path, which
 * reports the problem exactly as before, and resumes here after it. Nothing here raises on bad data.
 *
 * Format: the AEDAT 4.0 file format and the flatbuffers binary layout (see ev3dgs/io/flatbuf.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <stdint.h>
#include <string.h>
#include <pthread.h>
#include <unistd.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#if !defined(__BYTE_ORDER__) || __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "this module reads little-endian data in place: build it on a little-endian machine only"
#endif

typedef size_t (*lz4f_decompress_t)(void *, void *, size_t *, const void *, size_t *, const void *);
typedef void (*lz4f_reset_t)(void *);
typedef size_t (*zstd_decompress_t)(void *, void *, size_t, const void *, size_t);
typedef unsigned (*zstd_is_error_t)(size_t);

enum { ST_DONE = 0, ST_FULL = 1, ST_SLOW = 2 };

static inline uint16_t rd16(const uint8_t *p) { uint16_t v; memcpy(&v, p, 2); return v; }
static inline uint32_t rd32(const uint8_t *p) { uint32_t v; memcpy(&v, p, 4); return v; }
static inline int64_t rd64(const uint8_t *p) { int64_t v; memcpy(&v, p, 8); return v; }

/* The Event vector of a size-prefixed EVTS flatbuffer of n bytes: 0 and (*ev, *count), or -1 when anything
 * is out of place (the general path then says what). Mirrors flatbuf.root / Table.vector. */
static int parse_events(const uint8_t *b, uint64_t n, const uint8_t **ev, uint64_t *count)
{
    if (n < 4) return -1;
    uint64_t len = rd32(b);
    if (len + 4 > n || len < 8) return -1;
    const uint8_t *m = b + 4;
    if (memcmp(m + 4, "EVTS", 4) != 0) return -1;
    uint64_t pos = rd32(m);
    if (pos + 4 > len) return -1;
    int64_t vt = (int64_t)pos - (int64_t)(int32_t)rd32(m + pos);
    if (vt < 0 || (uint64_t)vt + 4 > len) return -1;
    uint64_t vt_size = rd16(m + vt), t_size = rd16(m + vt + 2);
    if (vt_size < 4 || vt_size % 2 || (uint64_t)vt + vt_size > len) return -1;
    if (t_size < 4 || pos + t_size > len) return -1;
    *count = 0;
    if (vt_size < 6) return 0;                      /* field 0 (the vector) absent: no events */
    uint64_t off = rd16(m + vt + 4);
    if (!off) return 0;
    if (off < 4 || off + 4 > t_size) return -1;
    uint64_t p = pos + off;
    uint64_t q = p + rd32(m + p);
    if (q + 4 > len) return -1;
    uint64_t c = rd32(m + q);
    if (q + 4 + 16 * c > len) return -1;
    *ev = m + q + 4;
    *count = c;
    return 0;
}

/* Unpack c Event structs (int64 t, int16 x, int16 y, uint8 polarity, 3 bytes padding) into t, x, y and p
 * (+1/-1); nonzero when the packet is not intact: time going backwards, a polarity byte other than 0/1, or
 * (width, height > 0) a coordinate outside the sensor. On x86-64, four events at a time with SSE2 (which every
 * x86-64 CPU has); the tail and other machines one at a time. Both compute the same outputs and verdict. */
static int unpack(const uint8_t *restrict ev, uint64_t c, int64_t *restrict t, uint16_t *restrict x,
                  uint16_t *restrict y, int8_t *restrict p, int width, int height)
{
    unsigned wm1 = (width > 0 && height > 0) ? (unsigned)width - 1 : 0xFFFFu;
    unsigned hm1 = (width > 0 && height > 0) ? (unsigned)height - 1 : 0xFFFFu;
    unsigned bad = 0;
    int64_t prev = c ? rd64(ev) : 0;
    uint64_t j = 0;
#if defined(__SSE2__)
    const __m128i flip = _mm_set1_epi16((short)0x8000);
    const __m128i lim = _mm_set_epi16((short)(hm1 ^ 0x8000u), (short)(hm1 ^ 0x8000u), (short)(hm1 ^ 0x8000u),
                                      (short)(hm1 ^ 0x8000u), (short)(wm1 ^ 0x8000u), (short)(wm1 ^ 0x8000u),
                                      (short)(wm1 ^ 0x8000u), (short)(wm1 ^ 0x8000u));
    const __m128i low8 = _mm_set1_epi32(0xFF), high7 = _mm_set1_epi32(0xFE), one8 = _mm_set1_epi8(1);
    __m128i vbad = _mm_setzero_si128(), vpol = _mm_setzero_si128();
    for (; j + 4 <= c; j += 4) {
        const uint8_t *e = ev + 16 * j;
        __m128i v0 = _mm_loadu_si128((const __m128i *)e), v1 = _mm_loadu_si128((const __m128i *)(e + 16));
        __m128i v2 = _mm_loadu_si128((const __m128i *)(e + 32)), v3 = _mm_loadu_si128((const __m128i *)(e + 48));
        _mm_storeu_si128((__m128i *)(t + j), _mm_unpacklo_epi64(v0, v1));
        _mm_storeu_si128((__m128i *)(t + j + 2), _mm_unpacklo_epi64(v2, v3));
        /* 32-bit lanes of the struct tails: [x0|y0, p0, x1|y1, p1] -> [x0|y0, x1|y1, p0, p1] */
        __m128i a = _mm_shuffle_epi32(_mm_unpackhi_epi64(v0, v1), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i b = _mm_shuffle_epi32(_mm_unpackhi_epi64(v2, v3), _MM_SHUFFLE(3, 1, 2, 0));
        __m128i xy = _mm_unpacklo_epi64(a, b);                     /* 16-bit: x0 y0 x1 y1 x2 y2 x3 y3 */
        __m128i pp = _mm_unpackhi_epi64(a, b);                     /* 32-bit: p0 p1 p2 p3 (+ padding) */
        __m128i s = _mm_shufflelo_epi16(xy, _MM_SHUFFLE(3, 1, 2, 0));
        s = _mm_shufflehi_epi16(s, _MM_SHUFFLE(3, 1, 2, 0));
        s = _mm_shuffle_epi32(s, _MM_SHUFFLE(3, 1, 2, 0));          /* x0 x1 x2 x3 y0 y1 y2 y3 */
        _mm_storel_epi64((__m128i *)(x + j), s);
        _mm_storel_epi64((__m128i *)(y + j), _mm_unpackhi_epi64(s, s));
        vbad = _mm_or_si128(vbad, _mm_cmpgt_epi16(_mm_xor_si128(s, flip), lim));   /* unsigned x > w - 1 */
        vpol = _mm_or_si128(vpol, _mm_and_si128(pp, high7));                        /* polarity byte > 1 */
        __m128i p16 = _mm_packs_epi32(_mm_and_si128(pp, low8), _mm_setzero_si128());
        __m128i p8 = _mm_packus_epi16(p16, _mm_setzero_si128());
        p8 = _mm_sub_epi8(_mm_add_epi8(p8, p8), one8);              /* 0 -> -1, 1 -> +1 */
        int32_t pv = _mm_cvtsi128_si32(p8);
        memcpy(p + j, &pv, 4);
        int64_t t0 = rd64(e), t1 = rd64(e + 16), t2 = rd64(e + 32), t3 = rd64(e + 48);
        bad |= (t0 < prev) | (t1 < t0) | (t2 < t1) | (t3 < t2);
        prev = t3;
    }
    bad |= (unsigned)_mm_movemask_epi8(vbad);                      /* compare results: all-ones bytes */
    bad |= _mm_movemask_epi8(_mm_cmpeq_epi8(vpol, _mm_setzero_si128())) != 0xFFFF;   /* any bit set */
#endif
    for (; j < c; j++) {
        const uint8_t *e = ev + 16 * j;
        int64_t tj = rd64(e);
        uint16_t xj = rd16(e + 8), yj = rd16(e + 10);
        uint8_t pj = e[12];
        bad |= (tj < prev) | (pj > 1) | (xj > wm1) | (yj > hm1);
        prev = tj;
        t[j] = tj;
        x[j] = xj;
        y[j] = yj;
        p[j] = (int8_t)(2 * (pj & 1) - 1);
    }
    return bad != 0;
}

static int read_full(int fd, uint8_t *buf, size_t n, int64_t at)
{
    size_t got = 0;
    while (got < n) {
        ssize_t r = pread(fd, buf + got, n - got, (off_t)(at + (int64_t)got));
        if (r < 0 && errno == EINTR) continue;
        if (r <= 0) return -1;
        got += (size_t)r;
    }
    return 0;
}

typedef struct { unsigned stable_dst, skip_checksums, reserved1, reserved0; } lz4f_options;

/* One call's work: packets a..kend-1, each unpacked at its own output position (known in advance from the
 * table's element counts), so that workers can take packets in any order; what depends on the packets
 * before (time order across packets) is checked afterwards, in file order. */
typedef struct {
    int fd, comp, sid, width, height;
    lz4f_decompress_t lz4;
    lz4f_reset_t lz4_reset;
    zstd_decompress_t zstd;
    zstd_is_error_t zstd_err;
    const int64_t *off, *size, *nel, *lo, *hi, *pos;    /* pos, ok: indexed by k - a */
    int64_t *ot, *sig;
    uint16_t *ox, *oy;
    int8_t *op, *ok;
    Py_ssize_t a, kend;
    Py_ssize_t next;                        /* next packet to take (workers share it; __atomic builtins) */
} job_t;

typedef struct {
    job_t *job;
    uint8_t *rb, *sc;
    size_t rb_len, sc_len;
    void *lz4_ctx, *zstd_ctx;
} worker_t;

/* Packet k read, decompressed, parsed, unpacked and checked on its own: 1 if intact (sig filled), else 0. */
static int one_packet(const job_t *j, const worker_t *w, Py_ssize_t k)
{
    int64_t n_el = j->nel[k], sz = j->size[k];
    uint8_t *rb = w->rb;
    if (read_full(j->fd, rb, (size_t)sz + 8, j->off[k] - 8)) return 0;
    if ((int32_t)rd32(rb) != j->sid || rd32(rb + 4) != (uint32_t)sz) return 0;
    const uint8_t *buf = rb + 8;
    uint64_t n = (uint64_t)sz;
    if (j->comp == 1 || j->comp == 2) {
        lz4f_options opts = {1, 0, 0, 0};  /* stableDst: the output stays put, linked blocks refer back into it */
        size_t dst = w->sc_len, src = (size_t)sz;
        size_t hint = j->lz4(w->lz4_ctx, w->sc, &dst, rb + 8, &src, &opts);
        if (hint != 0 || src != (size_t)sz) {  /* error, unfinished frame (too small), or trailing bytes */
            j->lz4_reset(w->lz4_ctx);
            return 0;
        }
        buf = w->sc;
        n = dst;
    } else if (j->comp == 3 || j->comp == 4) {
        size_t got = j->zstd(w->zstd_ctx, w->sc, w->sc_len, rb + 8, (size_t)sz);
        if (j->zstd_err(got)) return 0;
        buf = w->sc;
        n = got;
    }
    const uint8_t *ev = NULL;
    uint64_t c;
    if (parse_events(buf, n, &ev, &c) || c != (uint64_t)n_el) return 0;
    int64_t at = j->pos[k - j->a];
    if (unpack(ev, c, j->ot + at, j->ox + at, j->oy + at, j->op + at, j->width, j->height)) return 0;
    j->sig[3 * k] = (int64_t)c;
    if (c) {
        int64_t t0 = j->ot[at], t1 = j->ot[at + c - 1];
        if (t0 < j->lo[k] || t1 > j->hi[k]) return 0;         /* outside the table's time range */
        j->sig[3 * k + 1] = t0;
        j->sig[3 * k + 2] = t1;
    }
    return 1;
}

static void *work(void *arg)
{
    worker_t *w = arg;
    job_t *j = w->job;
    for (;;) {
        Py_ssize_t k = __atomic_fetch_add(&j->next, 1, __ATOMIC_RELAXED);
        if (k >= j->kend) break;
        j->ok[k - j->a] = (int8_t)one_packet(j, w, k);
    }
    return NULL;
}

#define MAX_THREADS 64

static const char doc_events[] =
    "events(fd, comp, lz4f_decompress, lz4f_reset, lz4_ctxs, zstd_decompress, zstd_is_error, zstd_ctxs, sid,\n"
    "       off, size, nel, lo, hi, a, b, readbufs, scratches, t, x, y, p, sig, width, height, has_last, last)\n"
    "-> (k, n_out, has_last, last, status): packets a..b-1 of the int64 arrays off/size/nel/lo/hi unpacked into\n"
    "t/x/y/p from index 0 on; sig[3k..3k+2] = (count, first t, last t) per committed packet. lz4_ctxs /\n"
    "zstd_ctxs: int64 arrays of decompression contexts, one per thread (their length is the thread count);\n"
    "readbufs / scratches: that many equal slices. status 0: all done, 1: packet k does not fit the output,\n"
    "2: packet k must take the general path.";

static PyObject *events(PyObject *self, PyObject *args)
{
    (void)self;
    int fd, comp, sid, width, height, has_last;
    unsigned long long lz4_fn, lz4_reset, zstd_fn, zstd_err;
    long long last;
    Py_ssize_t a, b;
    Py_buffer off_b, size_b, nel_b, lo_b, hi_b, lc_b, zc_b, rb_b, sc_b, t_b, x_b, y_b, p_b, sig_b;
    if (!PyArg_ParseTuple(args, "iiKKy*KKy*iy*y*y*y*y*nnw*w*w*w*w*w*w*iipL", &fd, &comp, &lz4_fn, &lz4_reset, &lc_b,
                          &zstd_fn, &zstd_err, &zc_b, &sid, &off_b, &size_b, &nel_b, &lo_b, &hi_b, &a, &b, &rb_b,
                          &sc_b, &t_b, &x_b, &y_b, &p_b, &sig_b, &width, &height, &has_last, &last))
        return NULL;
    Py_buffer *all[] = {&off_b, &size_b, &nel_b, &lo_b, &hi_b, &lc_b, &zc_b, &rb_b, &sc_b, &t_b, &x_b, &y_b,
                        &p_b, &sig_b};
    const size_t n_all = sizeof all / sizeof all[0];
    const int64_t *off = off_b.buf, *size = size_b.buf, *nel = nel_b.buf;
    Py_ssize_t npk = off_b.len / 8;
    Py_ssize_t nthreads = (comp == 0 ? (lc_b.len > zc_b.len ? lc_b.len : zc_b.len)
                                     : comp <= 2 ? lc_b.len : zc_b.len) / 8;
    uint64_t cap = (uint64_t)(t_b.len / 8);
    const void *const *lz4_ctxs = lc_b.buf, *const *zstd_ctxs = zc_b.buf;
    if (a < 0 || b > npk || a > b || size_b.len / 8 < npk || nel_b.len / 8 < npk || lo_b.len / 8 < npk ||
        hi_b.len / 8 < npk || (uint64_t)(x_b.len / 2) < cap || (uint64_t)(y_b.len / 2) < cap ||
        (uint64_t)p_b.len < cap || sig_b.len / 8 < 3 * npk || comp < 0 || comp > 4 || nthreads < 1 ||
        nthreads > MAX_THREADS || (comp && comp <= 2 && !(lz4_fn && lz4_reset)) ||
        (comp >= 3 && !(zstd_fn && zstd_err))) {
        for (size_t i = 0; i < n_all; i++) PyBuffer_Release(all[i]);
        PyErr_SetString(PyExc_ValueError, "_fast.events: inconsistent arguments");
        return NULL;
    }
    size_t rb_len = (size_t)rb_b.len / (size_t)nthreads, sc_len = (size_t)sc_b.len / (size_t)nthreads;

    /* which packets this call takes: up to the first that does not fit the output or the buffers */
    int64_t *pos = PyMem_Malloc(sizeof(int64_t) * (size_t)(b - a + 1));
    int8_t *ok = PyMem_Malloc((size_t)(b - a + 1));
    if (!pos || !ok) {
        PyMem_Free(pos);
        PyMem_Free(ok);
        for (size_t i = 0; i < n_all; i++) PyBuffer_Release(all[i]);
        return PyErr_NoMemory();
    }
    Py_ssize_t kend = a;
    int stop = ST_DONE;
    uint64_t acc = 0;
    for (; kend < b; kend++) {
        int64_t n_el = nel[kend], sz = size[kend];
        if (n_el < 0 || sz < 0 || off[kend] < 8 || (uint64_t)sz + 8 > rb_len) { stop = ST_SLOW; break; }
        if ((uint64_t)n_el > cap - acc) { stop = ST_FULL; break; }
        pos[kend - a] = (int64_t)acc;
        acc += (uint64_t)n_el;
    }
    job_t job = {fd, comp, sid, width, height, (lz4f_decompress_t)(uintptr_t)lz4_fn,
                 (lz4f_reset_t)(uintptr_t)lz4_reset, (zstd_decompress_t)(uintptr_t)zstd_fn,
                 (zstd_is_error_t)(uintptr_t)zstd_err, off, size, nel, lo_b.buf, hi_b.buf, pos, t_b.buf,
                 sig_b.buf, x_b.buf, y_b.buf, p_b.buf, ok, a, kend, a};
    worker_t workers[MAX_THREADS];
    if (nthreads > kend - a) nthreads = kend - a > 0 ? kend - a : 1;
    for (Py_ssize_t i = 0; i < nthreads; i++)
        workers[i] = (worker_t){&job, (uint8_t *)rb_b.buf + i * rb_len, (uint8_t *)sc_b.buf + i * sc_len, rb_len,
                                sc_len, comp && comp <= 2 ? (void *)lz4_ctxs[i] : NULL,
                                comp >= 3 ? (void *)zstd_ctxs[i] : NULL};
    Py_ssize_t k = a;
    uint64_t nout = 0;
    int status = stop;

    Py_BEGIN_ALLOW_THREADS
    pthread_t tid[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (Py_ssize_t i = 1; i < nthreads; i++)          /* a thread that cannot start leaves its share to the rest */
        started[i] = pthread_create(&tid[i], NULL, work, &workers[i]) == 0;
    work(&workers[0]);
    for (Py_ssize_t i = 1; i < nthreads; i++)
        if (started[i]) pthread_join(tid[i], NULL);
    /* commit in file order: intact, and after what was kept so far without ending at it (an all-equal packet
       at the last time kept could be a duplicate: the general path decides) */
    for (; k < kend; k++) {
        if (!ok[k - a]) { status = ST_SLOW; break; }
        int64_t c = job.sig[3 * k];
        if (c) {
            int64_t t0 = job.sig[3 * k + 1], t1 = job.sig[3 * k + 2];
            if (has_last && (t0 < last || t1 <= last)) { status = ST_SLOW; break; }
            last = t1;
            has_last = 1;
            nout = (uint64_t)(pos[k - a] + c);
        }
    }
    Py_END_ALLOW_THREADS

    PyMem_Free(pos);
    PyMem_Free(ok);
    for (size_t i = 0; i < n_all; i++) PyBuffer_Release(all[i]);
    return Py_BuildValue("nKiLi", k, (unsigned long long)nout, has_last, last, status);
}

static const char doc_table[] =
    "table(buf, start, count, offset, stream, size, elements, t_start, t_end) -> bool: the FileDataTable's\n"
    "vector of `count` PacketHeader tables at `start` of the flatbuffer `buf` into the six int64 arrays;\n"
    "False (arrays undefined) when any position or field is out of place: flatbuf.table_vector then says what.";

/* One field of a table: 0 and *v (0 when absent), -1 when it lies outside its table. */
static int field(const uint8_t *m, int64_t tpos, int64_t vt, uint64_t vt_size, uint64_t t_size, int slot, int delta,
                 int width, int is_signed32, int64_t *v)
{
    *v = 0;
    if (vt_size < (uint64_t)(6 + 2 * slot)) return 0;
    uint64_t off = rd16(m + vt + 4 + 2 * slot);
    if (!off) return 0;
    if (off < 4 || off + delta + width > t_size) return -1;
    const uint8_t *q = m + tpos + off + delta;
    *v = width == 8 ? rd64(q) : is_signed32 ? (int64_t)(int32_t)rd32(q) : (int64_t)rd32(q);
    return 0;
}

static PyObject *table(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer buf_b, o[6];
    Py_ssize_t start, count;
    if (!PyArg_ParseTuple(args, "y*nnw*w*w*w*w*w*", &buf_b, &start, &count, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    const uint8_t *m = buf_b.buf;
    int64_t n = buf_b.len;
    int ok = start >= 0 && count >= 0 && start + 4 * (int64_t)count <= n;
    for (int f = 0; f < 6; f++) ok = ok && o[f].len / 8 >= count;
    int64_t *off = o[0].buf, *sid = o[1].buf, *size = o[2].buf, *nel = o[3].buf, *t0 = o[4].buf, *t1 = o[5].buf;
    for (Py_ssize_t i = 0; ok && i < count; i++) {
        int64_t elem = start + 4 * (int64_t)i;
        int64_t tpos = elem + (int64_t)rd32(m + elem);
        if (tpos + 4 > n) { ok = 0; break; }
        int64_t vt = tpos - (int64_t)(int32_t)rd32(m + tpos);
        if (vt < 0 || vt + 4 > n) { ok = 0; break; }
        uint64_t vt_size = rd16(m + vt), t_size = rd16(m + vt + 2);
        if (vt_size < 4 || vt + (int64_t)vt_size > n || t_size < 4 || tpos + (int64_t)t_size > n) { ok = 0; break; }
        ok = !(field(m, tpos, vt, vt_size, t_size, 0, 0, 8, 0, off + i) ||
               field(m, tpos, vt, vt_size, t_size, 1, 0, 4, 1, sid + i) ||
               field(m, tpos, vt, vt_size, t_size, 1, 4, 4, 0, size + i) ||
               field(m, tpos, vt, vt_size, t_size, 2, 0, 8, 0, nel + i) ||
               field(m, tpos, vt, vt_size, t_size, 3, 0, 8, 0, t0 + i) ||
               field(m, tpos, vt, vt_size, t_size, 4, 0, 8, 0, t1 + i));
    }
    PyBuffer_Release(&buf_b);
    for (int f = 0; f < 6; f++) PyBuffer_Release(&o[f]);
    return PyBool_FromLong(ok);
}

static PyMethodDef methods[] = {
    {"events", events, METH_VARARGS, doc_events},
    {"table", table, METH_VARARGS, doc_table},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "ev3dgs.io.aedat4._fast",
                                    "AEDAT 4.0 events packets unpacked in C (see ev3dgs.io.aedat4_fast).", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__fast(void) { return PyModule_Create(&module); }
