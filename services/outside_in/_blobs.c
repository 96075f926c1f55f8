/* The compiled twin of services/outside_in/blobs.py's segmentation: the bright
 * 8-connected components of an 8-bit image (in the whole frame, or in windows), each
 * one's detector centroid (services/laser_camera/detection.py) and its refinement
 * (blobs._refine: centroid over the blob and its rim, the centroid's std, roundness).
 *
 * The same results as the Python path: the components come in the order it finds them
 * (bands of bright rows top to bottom, runs of bright columns in a band left to right,
 * and in each box or window the order of cv2.connectedComponents, which labels by the
 * first 2 x 2 block of a component in the box's raster of blocks); every sum of integer
 * values is exact in any order, and the one sum of fractions (the centroid variance's
 * moments) is taken in cv2.moments' order (32 x 32 tiles, row sums, the tiles moved to the
 * corner), compiled without floating-point contraction (setup.py); powers are libm's pow,
 * as Python's float ** 2.  The Python interpreter's work per blob was most of the cost
 * (about 70 us a blob, 15-20 blobs an image, 960 images a second at 8 cameras x 120 Hz).
 * The interpreter lock is released while it works.  Optional: when this does not build,
 * blobs.py runs in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* libm's pow, as Python's float ** 2 calls it: the compiler would turn pow(x, 2.0) into
 * x * x, which rounds otherwise in about one case of a thousand */
static double (*volatile libm_pow)(double, double) = pow;

typedef struct {
    int threshold, min_area, max_area;
    double dark, gain, two_rn, rn2, w_lo, floor2;
} params_t;

/* One component of a box or window: its bounding box (image pixels), pixel count,
 * detector centroid and flux. */
typedef struct {
    int x, y, w, h, area;
    double u, v, flux;
} comp_t;

typedef struct {
    comp_t *c;
    Py_ssize_t n, cap;
} comps_t;

typedef struct {
    const uint8_t *img;
    int H, W;
    params_t p;
    int32_t *labels;   /* scratch: a box's labels */
    int32_t *stack;    /* scratch: flood fill */
    size_t scratch;    /* elements of each */
} ctx_t;

static int grow_scratch(ctx_t *c, size_t n) {
    if (n <= c->scratch) return 1;
    int32_t *l = realloc(c->labels, n * sizeof(int32_t));
    if (!l) return 0;
    c->labels = l;
    int32_t *s = realloc(c->stack, n * sizeof(int32_t));
    if (!s) return 0;
    c->stack = s;
    c->scratch = n;
    return 1;
}

static int push(comps_t *cs, const comp_t *c) {
    if (cs->n == cs->cap) {
        Py_ssize_t cap = cs->cap ? 2 * cs->cap : 64;
        comp_t *n = realloc(cs->c, (size_t)cap * sizeof(comp_t));
        if (!n) return 0;
        cs->c = n;
        cs->cap = cap;
    }
    cs->c[cs->n++] = *c;
    return 1;
}

#define BRIGHT(ctx, yy, xx) ((ctx)->img[(size_t)(yy) * (ctx)->W + (xx)] > (ctx)->p.threshold)

/* The components of the box [x0, x1) x [y0, y1) in cv2.connectedComponents' order (by
 * their first 2 x 2 block); those of an area in [min_area, max_area] go to ``out``.
 * ``touch``: set when any component reaches an edge of the box that lies inside the
 * image (a window that cuts a blob).  0 on memory failure. */
static int label_box(ctx_t *c, int x0, int y0, int x1, int y1, comps_t *out, int *touch) {
    int bw = x1 - x0, bh = y1 - y0;
    size_t n = (size_t)bw * bh;
    if (!grow_scratch(c, n)) return 0;
    int32_t *lab = c->labels, *st = c->stack;
    memset(lab, 0, n * sizeof(int32_t));
    int32_t next = 0;
    for (int by = 0; by < bh; by += 2) {
        for (int bx = 0; bx < bw; bx += 2) {
            for (int k = 0; k < 4; k++) {
                int yy = by + (k >> 1), xx = bx + (k & 1);
                if (yy >= bh || xx >= bw) continue;
                size_t i = (size_t)yy * bw + xx;
                if (lab[i] || !BRIGHT(c, y0 + yy, x0 + xx)) continue;
                /* a new component: flood fill it, 8-connected, inside the box */
                next++;
                int minx = xx, maxx = xx, miny = yy, maxy = yy, area = 0;
                int64_t m00 = 0, m10 = 0, m01 = 0;
                size_t top = 0;
                lab[i] = next;
                st[top++] = (int32_t)i;
                /* pixel sums relative to the box corner; moved to the component's below */
                while (top) {
                    int32_t j = st[--top];
                    int py = j / bw, px = j % bw;
                    area++;
                    if (px < minx) minx = px;
                    if (px > maxx) maxx = px;
                    if (py < miny) miny = py;
                    if (py > maxy) maxy = py;
                    int s = (int)c->img[(size_t)(y0 + py) * c->W + x0 + px] - (int)c->p.dark;
                    if (s > 0) {
                        m00 += s;
                        m10 += (int64_t)s * px;
                        m01 += (int64_t)s * py;
                    }
                    for (int dy = -1; dy <= 1; dy++) {
                        int qy = py + dy;
                        if (qy < 0 || qy >= bh) continue;
                        for (int dx = -1; dx <= 1; dx++) {
                            int qx = px + dx;
                            if (qx < 0 || qx >= bw) continue;
                            size_t q = (size_t)qy * bw + qx;
                            if (!lab[q] && BRIGHT(c, y0 + qy, x0 + qx)) {
                                lab[q] = next;
                                st[top++] = (int32_t)q;
                            }
                        }
                    }
                }
                if (touch && ((minx == 0 && x0 > 0) || (maxx == bw - 1 && x1 < c->W)
                              || (miny == 0 && y0 > 0) || (maxy == bh - 1 && y1 < c->H)))
                    *touch = 1;
                if (area < c->p.min_area || area > c->p.max_area) continue;
                comp_t comp;
                comp.x = x0 + minx;
                comp.y = y0 + miny;
                comp.w = maxx - minx + 1;
                comp.h = maxy - miny + 1;
                comp.area = area;
                comp.flux = (double)m00;
                /* detection._centroid: the component's corner plus m10 / m00 about it */
                comp.u = (double)comp.x + (double)(m10 - m00 * minx) / (double)m00;
                comp.v = (double)comp.y + (double)(m01 - m00 * miny) / (double)m00;
                if (!push(out, &comp)) return 0;
            }
        }
    }
    return 1;
}

/* detection.windows_in: the windows clipped to the image, every overlapping pair
 * replaced by its bounding box until none overlap (in its order), empty ones left out;
 * ``b`` (k x 4) in place, the number kept returned. */
static Py_ssize_t join_windows(int64_t *b, Py_ssize_t k, int W, int H) {
    for (Py_ssize_t i = 0; i < k; i++) {
        int64_t *q = b + 4 * i;
        if (q[0] < 0) q[0] = 0;
        if (q[1] < 0) q[1] = 0;
        if (q[2] > W) q[2] = W;
        if (q[3] > H) q[3] = H;
    }
    Py_ssize_t i = 0;
    while (i < k) {
        int joined = 0;
        for (Py_ssize_t j = i + 1; j < k && !joined; j++) {
            int64_t *a = b + 4 * i, *c = b + 4 * j;
            if (a[0] < c[2] && c[0] < a[2] && a[1] < c[3] && c[1] < a[3]) {
                if (c[0] < a[0]) a[0] = c[0];
                if (c[1] < a[1]) a[1] = c[1];
                if (c[2] > a[2]) a[2] = c[2];
                if (c[3] > a[3]) a[3] = c[3];
                memmove(c, c + 4, (size_t)(k - j - 1) * 4 * sizeof(int64_t));
                k--;
                joined = 1;
            }
        }
        i = joined ? 0 : i + 1;   /* a grown box may now overlap an earlier one */
    }
    Py_ssize_t kept = 0;
    for (Py_ssize_t m = 0; m < k; m++) {
        int64_t *q = b + 4 * m;
        if (q[2] > q[0] && q[3] > q[1]) {
            memmove(b + 4 * kept, q, 4 * sizeof(int64_t));
            kept++;
        }
    }
    return kept;
}

/* A boolean array's runs of ones: [start, stop) pairs into ``runs``; their number. */
static int runs_of(const uint8_t *on, int n, int *runs) {
    int k = 0;
    for (int i = 0; i < n; i++) {
        if (!on[i]) continue;
        if (k && runs[2 * k - 1] == i) runs[2 * k - 1] = i + 1;
        else { runs[2 * k] = i; runs[2 * k + 1] = i + 1; k++; }
    }
    return k;
}

/* detection._components: the bands of bright rows, in each the runs of bright columns,
 * each box labelled. */
static int whole_frame(ctx_t *c, comps_t *out) {
    int H = c->H, W = c->W, ok = 0;
    uint8_t *row_on = calloc((size_t)H, 1), *col_on = malloc((size_t)W);
    int *rruns = malloc(sizeof(int) * (size_t)(H + 1)), *cruns = malloc(sizeof(int) * (size_t)(W + 1));
    if (!row_on || !col_on || !rruns || !cruns) goto done;
    for (int y = 0; y < H; y++) {   /* the row's maximum: a loop the compiler vectorises */
        const uint8_t *r = c->img + (size_t)y * W;
        uint8_t mx = 0;
        for (int x = 0; x < W; x++) mx = r[x] > mx ? r[x] : mx;
        row_on[y] = mx > c->p.threshold;
    }
    int nb = runs_of(row_on, H, rruns);
    for (int b = 0; b < nb; b++) {
        int r0 = rruns[2 * b], r1 = rruns[2 * b + 1];
        memset(col_on, 0, (size_t)W);
        const uint8_t thr = (uint8_t)c->p.threshold;
        for (int y = r0; y < r1; y++) {
            const uint8_t *r = c->img + (size_t)y * W;
            for (int x = 0; x < W; x++) col_on[x] |= r[x] > thr;
        }
        int nc = runs_of(col_on, W, cruns);
        for (int k = 0; k < nc; k++) {
            int c0 = cruns[2 * k], c1 = cruns[2 * k + 1];
            if ((c1 - c0) * (r1 - r0) < c->p.min_area) continue;  /* a hot pixel */
            if (!label_box(c, c0, r0, c1, r1, out, NULL)) goto done;
        }
    }
    ok = 1;
done:
    free(row_on); free(col_on); free(rruns); free(cruns);
    return ok;
}

/* cv2.moments' m00, m10, m01, m20, m11, m02 of a float64 image (h x w, row-major), in its
 * order of operations: 32 x 32 tiles, per row the sums of p, x p, x x p, the tile's
 * moments about its corner moved to the image's. */
static void moments(const double *img, int h, int w, double m[6]) {
    const int T = 32;
    for (int k = 0; k < 6; k++) m[k] = 0.0;
    for (int ty = 0; ty < h; ty += T) {
        int th = h - ty < T ? h - ty : T;
        for (int tx = 0; tx < w; tx += T) {
            int tw = w - tx < T ? w - tx : T;
            double mom[6] = {0, 0, 0, 0, 0, 0};
            for (int y = 0; y < th; y++) {
                const double *ptr = img + (size_t)(ty + y) * w + tx;
                double x0 = 0, x1 = 0, x2 = 0;
                for (int x = 0; x < tw; x++) {
                    double p = ptr[x];
                    double xp = x * p, xxp;
                    x0 += p;
                    x1 += xp;
                    xxp = xp * x;
                    x2 += xxp;
                }
                double py = y * x0, sy = y * y;
                mom[5] += x0 * sy;
                mom[4] += x1 * y;
                mom[3] += x2;
                mom[2] += py;
                mom[1] += x1;
                mom[0] += x0;
            }
            double xm = tx * mom[0], ym = ty * mom[0];
            m[0] += mom[0];
            m[1] += mom[1] + xm;
            m[2] += mom[2] + ym;
            m[3] += mom[3] + tx * (mom[1] * 2 + xm);
            m[4] += mom[4] + tx * (mom[2] + ym) + ty * mom[1];
            m[5] += mom[5] + ty * (mom[2] * 2 + ym);
        }
    }
}

/* 5 x 5 dilation of a 0/1 image inside the ROI (outside pixels count as off), as
 * cv2.dilate with the rim's kernel: the OR over +-2 along the rows, then along the
 * columns. */
static void dilate5(const uint8_t *src, uint8_t *tmp, uint8_t *dst, int h, int w) {
    for (int y = 0; y < h; y++) {
        const uint8_t *s = src + y * w;
        uint8_t *t = tmp + y * w;
        for (int x = 0; x < w; x++) {
            int lo = x - 2 < 0 ? 0 : x - 2, hi = x + 2 >= w ? w - 1 : x + 2;
            uint8_t v = 0;
            for (int k = lo; k <= hi; k++) v |= s[k];
            t[x] = v;
        }
    }
    for (int y = 0; y < h; y++) {
        int lo = y - 2 < 0 ? 0 : y - 2, hi = y + 2 >= h ? h - 1 : y + 2;
        uint8_t *d = dst + y * w;
        memcpy(d, tmp + lo * w, (size_t)w);
        for (int k = lo + 1; k <= hi; k++) {
            const uint8_t *t = tmp + k * w;
            for (int x = 0; x < w; x++) d[x] |= t[x];
        }
    }
}

/* blobs._refine of one component: out = u, v, std, roundness.  0 on memory failure. */
static int refine(ctx_t *c, const comp_t *comp, double out[4]) {
    const params_t *p = &c->p;
    int half = (int)ceil(sqrt((double)comp->area)) + 3;
    int u = (int)nearbyint(comp->u), v = (int)nearbyint(comp->v);
    int y0 = v - half > 0 ? v - half : 0, y1 = v + half + 1 < c->H ? v + half + 1 : c->H;
    int x0 = u - half > 0 ? u - half : 0, x1 = u + half + 1 < c->W ? u + half + 1 : c->W;
    int h = y1 - y0, w = x1 - x0;
    size_t n = (size_t)h * w;
    uint8_t *buf = malloc(5 * n);
    double *sig = malloc(2 * n * sizeof(double));
    int32_t *st = malloc(n * sizeof(int32_t));
    if (!buf || !sig || !st) { free(buf); free(sig); free(st); return 0; }
    uint8_t *bright = buf, *mine = buf + n, *other = buf + 2 * n, *tmp = buf + 3 * n,
            *dil = buf + 4 * n;
    double *var = sig + n;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++)
            bright[y * w + x] = c->img[(size_t)(y0 + y) * c->W + x0 + x] > p->threshold;
    int sy = v - y0, sx = u - x0;
    sy = sy < 0 ? 0 : (sy > h - 1 ? h - 1 : sy);
    sx = sx < 0 ? 0 : (sx > w - 1 ? w - 1 : sx);
    if (bright[sy * w + sx]) {   /* the component holding the centroid's pixel */
        memset(mine, 0, n);
        size_t top = 0;
        mine[sy * w + sx] = 1;
        st[top++] = sy * w + sx;
        while (top) {
            int j = st[--top], py = j / w, px = j % w;
            for (int dy = -1; dy <= 1; dy++) {
                int qy = py + dy;
                if (qy < 0 || qy >= h) continue;
                for (int dx = -1; dx <= 1; dx++) {
                    int qx = px + dx;
                    if (qx < 0 || qx >= w) continue;
                    int q = qy * w + qx;
                    if (bright[q] && !mine[q]) { mine[q] = 1; st[top++] = q; }
                }
            }
        }
    } else {                     /* between the pixels of a ring: all bright pixels */
        memcpy(mine, bright, n);
    }
    for (size_t i = 0; i < n; i++) other[i] = bright[i] & !mine[i];
    dilate5(other, tmp, other, h, w);   /* other := its dilation (tmp holds the rows) */
    dilate5(mine, tmp, dil, h, w);
    for (int y = 0; y < h; y++) {
        const uint8_t *row = c->img + (size_t)(y0 + y) * c->W + x0;
        for (int x = 0; x < w; x++) {
            int i = y * w + x, sel = dil[i] & !other[i];
            uint8_t px = row[x];
            double s = (double)px - p->dark;
            if (!(s >= 0.0)) s = 0.0;   /* np.maximum(s, 0) */
            s *= sel;
            sig[i] = s;
            double read = (s > p->two_rn ? 1.0 : p->w_lo) * p->rn2;
            var[i] = (s * p->gain + read) * (double)(sel & (px < 255));
        }
    }
    double m[6], mv[6];
    moments(sig, h, w, m);
    double flux = m[0];
    if (flux <= 0) {
        out[0] = comp->u; out[1] = comp->v; out[2] = INFINITY; out[3] = 0.0;
    } else {
        moments(var, h, w, mv);
        double cu = m[1] / flux, cv = m[2] / flux;
        double r2 = mv[3] + mv[5] - 2.0 * (cu * mv[1] + cv * mv[2]) + (cu * cu + cv * cv) * mv[0];
        double std = sqrt(0.5 * r2 / libm_pow(flux, 2.0) + p->floor2);
        /* cv2.moments' central moments (completeMomentState) */
        double inv = 1. / m[0], cx = m[1] * inv, cy = m[2] * inv;
        double mu20 = m[3] - m[1] * cx, mu11 = m[4] - m[1] * cy, mu02 = m[5] - m[2] * cy;
        double a = mu20 / flux, b = mu02 / flux, cc = mu11 / flux;
        double d = libm_pow(a - b, 2.0) + 4 * cc * cc;
        double root = sqrt(d > 0.0 ? d : 0.0);
        double big = 0.5 * (a + b + root), small = 0.5 * (a + b - root);
        out[0] = x0 + cu;
        out[1] = y0 + cv;
        out[2] = std;
        out[3] = big > 0 ? sqrt((small > 0.0 ? small : 0.0) / big) : 0.0;
    }
    free(buf); free(sig); free(st);
    return 1;
}

/* find(image, windows, threshold, min_area, max_area, dark, gain, two_rn, rn2, w_lo,
 *      floor2) -> (rows, whole)
 * image: C-contiguous uint8 (H, W); windows: None (the whole frame) or C-contiguous int64
 * (k, 4) of x0, y0, x1, y1 (clipped and joined here, as detection.windows_in does).  rows: bytes of float64 (n, 6): u, v, std,
 * roundness (refined), flux, area (the detector's).  whole: False when a window cut a
 * component (the caller then searches the whole frame). */
static PyObject *find(PyObject *self, PyObject *args) {
    PyObject *image, *windows;
    params_t p;
    if (!PyArg_ParseTuple(args, "OOiiidddddd", &image, &windows, &p.threshold, &p.min_area,
                          &p.max_area, &p.dark, &p.gain, &p.two_rn, &p.rn2, &p.w_lo,
                          &p.floor2))
        return NULL;
    Py_buffer img, win;
    int have_win = windows != Py_None;
    if (PyObject_GetBuffer(image, &img, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    if (img.ndim != 2 || img.itemsize != 1 || !img.format || strcmp(img.format, "B") != 0) {
        PyBuffer_Release(&img);
        PyErr_SetString(PyExc_ValueError, "image: expected a C-contiguous 2-D uint8 array");
        return NULL;
    }
    Py_ssize_t nwin = 0;
    if (have_win) {
        if (PyObject_GetBuffer(windows, &win, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
            PyBuffer_Release(&img);
            return NULL;
        }
        if (win.itemsize != 8 || win.len % 32 || !win.format
            || (strcmp(win.format, "l") && strcmp(win.format, "q") && strcmp(win.format, "<q")
                && strcmp(win.format, "<l"))) {
            PyBuffer_Release(&img);
            PyBuffer_Release(&win);
            PyErr_SetString(PyExc_ValueError, "windows: expected a contiguous int64 (k, 4)");
            return NULL;
        }
        nwin = win.len / 32;
    }
    int64_t *boxes = NULL;
    if (nwin) {
        boxes = malloc((size_t)win.len);
        if (!boxes) {
            PyBuffer_Release(&img);
            PyBuffer_Release(&win);
            return PyErr_NoMemory();
        }
        memcpy(boxes, win.buf, (size_t)win.len);
    }
    ctx_t c = {img.buf, (int)img.shape[0], (int)img.shape[1], p, NULL, NULL, 0};
    comps_t comps = {NULL, 0, 0};
    double *rows = NULL;
    int ok = 1, touch = 0;
    Py_BEGIN_ALLOW_THREADS
    if (have_win) {
        nwin = join_windows(boxes, nwin, c.W, c.H);
        for (Py_ssize_t k = 0; k < nwin && ok; k++)
            ok = label_box(&c, (int)boxes[4 * k], (int)boxes[4 * k + 1],
                           (int)boxes[4 * k + 2], (int)boxes[4 * k + 3], &comps, &touch);
    } else {
        ok = whole_frame(&c, &comps);
    }
    if (ok == 1 && comps.n) {
        rows = malloc((size_t)comps.n * 6 * sizeof(double));
        if (!rows) ok = 0;
        for (Py_ssize_t i = 0; i < comps.n && ok == 1; i++) {
            double r[4];
            if (!refine(&c, &comps.c[i], r)) { ok = 0; break; }
            memcpy(rows + 6 * i, r, sizeof r);
            rows[6 * i + 4] = comps.c[i].flux;
            rows[6 * i + 5] = (double)comps.c[i].area;
        }
    }
    Py_END_ALLOW_THREADS
    free(c.labels);
    free(c.stack);
    PyBuffer_Release(&img);
    if (have_win) PyBuffer_Release(&win);
    PyObject *res = NULL;
    if (ok == 1) {
        PyObject *b = PyBytes_FromStringAndSize((const char *)rows,
                                                (Py_ssize_t)(comps.n * 6 * sizeof(double)));
        if (b) res = Py_BuildValue("(NO)", b, touch ? Py_False : Py_True);
    } else {
        PyErr_NoMemory();
    }
    free(rows);
    free(boxes);
    free(comps.c);
    return res;
}

/* ---- blob_model.fit_centres: a blurred ball's image fitted to each blob's pixels ---- */

#define FIT_PASSES 1
#define FIT_STEPS 3
#define FIT_MAX_SHIFT 0.5
#define FIT_MISFIT_SIGMAS 3.0
#define FIT_MAX_PIX 169   /* (2 * 6 + 1)^2: the largest square */
static const double fit_lo[6] = {1.0, -INFINITY, -INFINITY, 0.05, 0.2, -INFINITY};
static const double fit_hi[6] = {INFINITY, INFINITY, INFINITY, 8.0, 3.0, INFINITY};

/* The model's pixels m and Jacobian J (n x 6) at x = amplitude, u, v, radius, blur,
 * background (blob_model._model). */
static void fit_model(const double *x, const double *px, const double *py, int n,
                      double *m, double *J) {
    const double a = x[0], cu = x[1], cv = x[2], r = x[3], s = x[4], b = x[5];
    const double sq2 = sqrt(2.0), sqpi = sqrt(M_PI);
    for (int k = 0; k < n; k++) {
        double du = px[k] - cu, dv = py[k] - cv;
        double d = sqrt(du * du + dv * dv);
        double z = (d - r) / (sq2 * s);
        double e = erfc(z);
        m[k] = b + 0.5 * a * e;
        double g = -a * exp(-z * z) / (sqpi * sq2 * s);
        double ux = d > 0 ? du / d : 0.0, uy = d > 0 ? dv / d : 0.0;
        double *j = J + 6 * k;
        j[0] = 0.5 * e; j[1] = -g * ux; j[2] = -g * uy; j[3] = -g; j[4] = -g * (d - r) / s;
        j[5] = 1.0;
    }
}

/* Solve A x = b (6 x 6, Gaussian elimination with partial pivoting, A and b destroyed);
 * 0 when A is singular. */
static int solve6(double A[6][6], double *b, double *x) {
    for (int c = 0; c < 6; c++) {
        int piv = c;
        for (int r = c + 1; r < 6; r++)
            if (fabs(A[r][c]) > fabs(A[piv][c])) piv = r;
        if (!(A[piv][c] != 0.0)) return 0;
        if (piv != c) {
            for (int k = 0; k < 6; k++) { double t = A[c][k]; A[c][k] = A[piv][k]; A[piv][k] = t; }
            double t = b[c]; b[c] = b[piv]; b[piv] = t;
        }
        for (int r = c + 1; r < 6; r++) {
            double f = A[r][c] / A[c][c];
            for (int k = c; k < 6; k++) A[r][k] -= f * A[c][k];
            b[r] -= f * b[c];
        }
    }
    for (int r = 5; r >= 0; r--) {
        double acc = b[r];
        for (int k = r + 1; k < 6; k++) acc -= A[r][k] * x[k];
        x[r] = acc / A[r][r];
    }
    return 1;
}

static void fit_normal(const double *J, const double *w, const double *res, int n,
                       double H[6][6], double *g) {
    memset(H, 0, 36 * sizeof(double));
    memset(g, 0, 6 * sizeof(double));
    for (int k = 0; k < n; k++) {
        if (w[k] == 0.0) continue;
        const double *j = J + 6 * k;
        for (int a = 0; a < 6; a++) {
            double wa = w[k] * j[a];
            g[a] += wa * (res ? res[k] : 0.0);
            for (int b = 0; b <= a; b++) H[a][b] += wa * j[b];
        }
    }
    for (int a = 0; a < 6; a++)
        for (int b = a + 1; b < 6; b++) H[a][b] = H[b][a];
}

/* Each pixel's weight (its noise from the model m: shot and read), residual, and the
 * weighted cost. */
static double fit_weights(const double *m, const double *use, const double *pix, int n,
                          double dark, double gain, double read2, double *w, double *res) {
    double cost = 0.0;
    for (int k = 0; k < n; k++) {
        double sig = m[k] - dark;
        w[k] = use[k] / (gain * (sig > 0.0 ? sig : 0.0) + read2);
        res[k] = m[k] - pix[k];
        cost += w[k] * res[k] * res[k];
    }
    return cost;
}

/* One blob's fit (blob_model._fit_group for one blob): out = u, v, std, fitted. */
static void fit_one(const uint8_t *img, int H, int W, const double *uv, const double *area,
                    Py_ssize_t n, Py_ssize_t i, double dark, double gain, double rn,
                    double *out) {
    out[0] = uv[2 * i]; out[1] = uv[2 * i + 1]; out[2] = NAN; out[3] = 0.0;
    int half = (int)(ceil(sqrt(area[i] / M_PI)) + 1);
    half = half < 2 ? 2 : (half > 6 ? 6 : half);
    int cu0 = (int)rint(uv[2 * i]), cv0 = (int)rint(uv[2 * i + 1]);
    if (!(cu0 >= half && cu0 < W - half && cv0 >= half && cv0 < H - half)) return;
    double px[FIT_MAX_PIX], py[FIT_MAX_PIX], pix[FIT_MAX_PIX], use[FIT_MAX_PIX];
    double m[FIT_MAX_PIX], J[6 * FIT_MAX_PIX], w[FIT_MAX_PIX], res[FIT_MAX_PIX];
    double tm[FIT_MAX_PIX], tJ[6 * FIT_MAX_PIX], tres[FIT_MAX_PIX];
    int np_ = 0;
    double peak = 0.0;
    /* the blobs near enough to own a pixel of the square */
    double reach = 2.0 * (half + 1.0) * sqrt(2.0);
    for (int y = cv0 - half; y <= cv0 + half; y++) {
        for (int x = cu0 - half; x <= cu0 + half; x++) {
            double v = img[(size_t)y * W + x];
            double ou = x - uv[2 * i], ov = y - uv[2 * i + 1];
            double d_own = sqrt(ou * ou + ov * ov);
            int own = 1;
            for (Py_ssize_t j = 0; j < n && own; j++) {
                if (j == i || fabs(uv[2 * j] - uv[2 * i]) > reach
                    || fabs(uv[2 * j + 1] - uv[2 * i + 1]) > reach) continue;
                double ju = x - uv[2 * j], jv = y - uv[2 * j + 1];
                own = sqrt(ju * ju + jv * jv) >= d_own;
            }
            px[np_] = x; py[np_] = y; pix[np_] = v;
            use[np_] = (v < 255 && own) ? 1.0 : 0.0;
            if (v > peak) peak = v;
            np_++;
        }
    }
    double r0 = sqrt(area[i] / M_PI) - 0.5;
    double x[6] = {peak - dark > 10.0 ? peak - dark : 10.0, uv[2 * i], uv[2 * i + 1],
                   r0 > 1.0 ? r0 : 1.0, 0.7, dark};
    double read2 = rn * rn + 1.0 / 12.0;
    fit_model(x, px, py, np_, m, J);
    double cost = 0.0;
    int used = 0;
    for (int k = 0; k < np_; k++) used += use[k] != 0.0;
    for (int pass = 0; pass < FIT_PASSES; pass++) {
        cost = fit_weights(m, use, pix, np_, dark, gain, read2, w, res);
        double lam = 1e-3;
        for (int step = 0; step < FIT_STEPS; step++) {
            double Hm[6][6], g[6], dx[6] = {0}, trial[6];
            fit_normal(J, w, res, np_, Hm, g);
            for (int a = 0; a < 6; a++) { Hm[a][a] += lam * Hm[a][a]; g[a] = -g[a]; }
            if (!solve6(Hm, g, dx)) memset(dx, 0, sizeof dx);
            for (int a = 0; a < 6; a++) {
                double t = x[a] + dx[a];
                trial[a] = t < fit_lo[a] ? fit_lo[a] : (t > fit_hi[a] ? fit_hi[a] : t);
            }
            fit_model(trial, px, py, np_, tm, tJ);
            double tcost = 0.0;
            for (int k = 0; k < np_; k++) {
                tres[k] = tm[k] - pix[k];
                tcost += w[k] * tres[k] * tres[k];
            }
            if (tcost < cost) {
                memcpy(x, trial, sizeof x);
                memcpy(m, tm, (size_t)np_ * sizeof(double));
                memcpy(J, tJ, (size_t)np_ * 6 * sizeof(double));
                memcpy(res, tres, (size_t)np_ * sizeof(double));
                cost = tcost;
                lam /= 3.0;
            } else {
                lam *= 4.0;
            }
        }
    }
    /* the covariance and misfit with the weights of the model reached */
    cost = fit_weights(m, use, pix, np_, dark, gain, read2, w, res);
    /* the centre's variance: the (u, v) diagonal of the information's inverse */
    double info[6][6], g[6], var = 0.0;
    fit_normal(J, w, NULL, np_, info, g);
    for (int c = 1; c <= 2; c++) {
        double A[6][6], e[6] = {0}, col[6];
        memcpy(A, info, sizeof A);
        e[c] = 1.0;
        if (!solve6(A, e, col)) return;
        var += 0.5 * col[c];
    }
    /* a blob the model does not describe: its std grows by sqrt(cost per dof) where that
     * is 3 of its stds over 1 (blob_model._misfit) */
    int dof = used - 6;
    double per_dof = cost / (dof > 1 ? dof : 1);
    if (per_dof > 1.0 + FIT_MISFIT_SIGMAS * sqrt(2.0 / (dof > 1 ? dof : 1))) var *= per_dof;
    int finite = 1;
    for (int a = 0; a < 6; a++) finite = finite && isfinite(x[a]);
    if (!(finite && var > 0 && dof > 0
          && hypot(x[1] - uv[2 * i], x[2] - uv[2 * i + 1]) <= FIT_MAX_SHIFT)) return;
    out[0] = x[1]; out[1] = x[2]; out[2] = sqrt(var); out[3] = 1.0;
}

/* fit(image, uv, area, which, dark, gain, read_noise) -> bytes of float64 (n, 4): each
 * blob's fitted u, v, std and 1.0 where it was fitted (else its centroid, nan, 0.0).
 * image: C-contiguous uint8 (H, W); uv: C-contiguous float64 (n, 2); area: float64 (n,);
 * which: uint8 (n,), the blobs to fit (all of them leave their pixels out of the others'). */
static PyObject *fit(PyObject *self, PyObject *args) {
    PyObject *image, *uvo, *areao, *whicho;
    double dark, gain, rn;
    if (!PyArg_ParseTuple(args, "OOOOddd", &image, &uvo, &areao, &whicho, &dark, &gain, &rn))
        return NULL;
    Py_buffer img, uv, area, which;
    if (PyObject_GetBuffer(image, &img, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    if (img.ndim != 2 || img.itemsize != 1 || !img.format || strcmp(img.format, "B") != 0) {
        PyBuffer_Release(&img);
        PyErr_SetString(PyExc_ValueError, "image: expected a C-contiguous 2-D uint8 array");
        return NULL;
    }
    if (PyObject_GetBuffer(uvo, &uv, PyBUF_C_CONTIGUOUS) < 0) {
        PyBuffer_Release(&img);
        return NULL;
    }
    if (PyObject_GetBuffer(areao, &area, PyBUF_C_CONTIGUOUS) < 0) {
        PyBuffer_Release(&img);
        PyBuffer_Release(&uv);
        return NULL;
    }
    if (PyObject_GetBuffer(whicho, &which, PyBUF_C_CONTIGUOUS) < 0) {
        PyBuffer_Release(&img); PyBuffer_Release(&uv); PyBuffer_Release(&area);
        return NULL;
    }
    Py_ssize_t n = area.len / (Py_ssize_t)sizeof(double);
    if (uv.itemsize != 8 || area.itemsize != 8 || uv.len != 2 * area.len
        || which.itemsize != 1 || which.len != n) {
        PyBuffer_Release(&img); PyBuffer_Release(&uv); PyBuffer_Release(&area);
        PyBuffer_Release(&which);
        PyErr_SetString(PyExc_ValueError,
                        "uv, area, which: expected float64 (n, 2), (n,) and uint8 (n,)");
        return NULL;
    }
    PyObject *res = PyBytes_FromStringAndSize(NULL, n * 4 * (Py_ssize_t)sizeof(double));
    if (res) {
        double *out = (double *)PyBytes_AS_STRING(res);
        const uint8_t *pixels = img.buf;
        int H = (int)img.shape[0], W = (int)img.shape[1];
        Py_BEGIN_ALLOW_THREADS
        const uint8_t *fit_it = which.buf;
        const double *c = uv.buf;
        for (Py_ssize_t i = 0; i < n; i++) {
            double *o = out + 4 * i;
            if (fit_it[i]) {
                fit_one(pixels, H, W, uv.buf, area.buf, n, i, dark, gain, rn, o);
            } else {
                o[0] = c[2 * i]; o[1] = c[2 * i + 1]; o[2] = NAN; o[3] = 0.0;
            }
        }
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&img); PyBuffer_Release(&uv); PyBuffer_Release(&area);
    PyBuffer_Release(&which);
    return res;
}

static PyMethodDef methods[] = {
    {"find", find, METH_VARARGS,
     "Bright blobs of an 8-bit image: refined centroid, std, roundness, flux, area."},
    {"fit", fit, METH_VARARGS,
     "Blob centres by a blurred ball's image fitted to the pixels: u, v, std, fitted."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_blobs", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__blobs(void) { return uma_twin_module(&module); }
