/* The compiled twin of the laser tracker's installation estimate arithmetic on small
 * arrays: tracker.py's _dot_moves (how far each of a pose's dots moves along its wall's
 * axes per one std of each installation parameter, scattered into the parameters'
 * columns), _installation_covariances (each labeling's dots' in-plane covariance from the
 * installation's tolerances, and the slopes it takes) and installation_estimate.py's
 * innovation and rank-2 Kalman update; pose.py's labelings of four dots (eq. 5.6's eps of
 * all 24, their P0 and rays) and the rig frames of labeled dots (frames_from_points,
 * _rotations).
 *
 * The same arithmetic as the numpy code, operation by operation, compiled without
 * floating-point contraction, its 3-term sums in the order numpy's einsum and add.reduce
 * take them (dot3, norm3): the covariances, labelings and frames agree with numpy's to the
 * bit where numpy sums so (its SIMD einsum on x86-64), the moves to rounding (the rig's
 * rotation from the quaternion by its formula, not numpy's product), the estimate's
 * update, whose numpy matrix products sum in BLAS's order, to rounding (a few 1e-16).
 * Why compiled: a frame set spends some hundred numpy calls here on a few hundred numbers,
 * the interpreter's cost rather than the arithmetic's.  Optional: when this does not
 * build, tracker.py, pose.py and installation_estimate.py run in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define NBUF 15

typedef struct {
    Py_buffer b[NBUF];
    int n;
} buffers_t;

static void release(buffers_t *bufs) {
    for (int i = 0; i < bufs->n; i++) PyBuffer_Release(&bufs->b[i]);
}

static int sized(const Py_buffer *b, Py_ssize_t n, const char *what) {
    if (b->len == n * (Py_ssize_t)sizeof(double)) return 1;
    PyErr_Format(PyExc_ValueError, "laser kernel: %s holds %zd bytes, expected %zd doubles",
                 what, b->len, n);
    return 0;
}

/* Whether a buffer holds 8-byte items of float64 (integer: int64), in native byte order. */
static int of_kind(const Py_buffer *b, int integer) {
    const char *f = b->format;
    if (f == NULL || b->itemsize != 8) return 0;
    if (*f == '@' || *f == '=' || *f == '<') f++;
    return integer ? !strcmp(f, "l") || !strcmp(f, "q") : !strcmp(f, "d");
}

/* Gets n buffers of o (float64; int64 where integer[i]; writable from index writable on),
 * checked; 0 (error set, released) if one is not. */
static int get_all(PyObject **o, int n, const int *integer, int writable, buffers_t *s) {
    for (int i = 0; i < n; i++) {
        int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (i >= writable ? PyBUF_WRITABLE : 0);
        if (PyObject_GetBuffer(o[i], &s->b[i], flags) < 0) { release(s); return 0; }
        s->n++;
        int ints = integer != NULL && integer[i];
        if (!of_kind(&s->b[i], ints)) {
            PyErr_Format(PyExc_ValueError, "laser kernel: argument %d is not a contiguous %s array",
                         i, ints ? "int64" : "float64");
            release(s);
            return 0;
        }
    }
    return 1;
}

/* A 3-term dot product summed as numpy's einsum sums one (two SIMD lanes: the first and
 * third products, then the second), so that the twins round as the numpy code does. */
static double dot3(const double *a, const double *b) { return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]; }

/* A 3-vector's norm summed as np.add.reduce sums (in order): pose.row_norms */
static double norm3(const double *a) { return sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]); }

/* geometry.quat_to_matrix of a unit quaternion (x, y, z, w), row-major */
static void quat_matrix(const double *q, double R[9]) {
    double x = q[0], y = q[1], z = q[2], w = q[3];
    R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - z * w);     R[2] = 2 * (x * z + y * w);
    R[3] = 2 * (x * y + z * w);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - x * w);
    R[6] = 2 * (x * z - y * w);     R[7] = 2 * (y * z + x * w);     R[8] = 1 - 2 * (x * x + y * y);
}

/* The block of moves of dot k (2 axes x width): its beam's tilt a, offset a, tilt b,
 * offset b, its screen's bend, its camera's turn (three axes) or residual (two), its
 * camera's map (eight coefficients, where cam >= 0). */
static void dot_block(const double *x, const double *A, const double *p0, const double R[9],
                      const double *across_rig, double shape, const double *bend,
                      const double *turn, long cam, const double *T, const double *Rot,
                      const double *side, const double *sigma, const double *std,
                      Py_ssize_t width, double *block) {
    const double *A0 = A, *A1 = A + 3;
    double n[3] = {A0[1] * A1[2] - A0[2] * A1[1], A0[2] * A1[0] - A0[0] * A1[2],
                   A0[0] * A1[1] - A0[1] * A1[0]};
    double d[3] = {x[0] - p0[0], x[1] - p0[1], x[2] - p0[2]};
    double r = sqrt(dot3(d, d));
    double unit[3] = {d[0] / r, d[1] / r, d[2] / r};
    double dn = dot3(n, d);
    double c0 = fabs(dn) / r;  /* cos(incidence), at least 0.05 (NaN stays NaN: np.maximum) */
    double nd = (dn < 0 ? -1.0 : 1.0) * (c0 < 0.05 ? 0.05 : c0);
    double slant[3] = {unit[0] / nd, unit[1] / nd, unit[2] / nd};
    double beam[2][2];  /* beam[a][b]: the dot's move along wall axis b per unit across a */
    for (int a = 0; a < 2; a++) {
        const double *e = across_rig + 3 * a;
        double c[3], w[3];
        for (int i = 0; i < 3; i++) c[i] = dot3(R + 3 * i, e);
        double along = dot3(c, unit);
        for (int i = 0; i < 3; i++) c[i] -= along * unit[i];
        double toward = dot3(c, n);
        for (int i = 0; i < 3; i++) w[i] = c[i] - toward * slant[i];
        for (int b = 0; b < 2; b++) beam[a][b] = dot3(A + 3 * b, w);
    }
    double scale[2] = {r * std[0], std[1]};
    double bulge = std[2] * shape;
    for (int b = 0; b < 2; b++) {
        double *row = block + b * width;
        for (int a = 0; a < 2; a++)
            for (int s = 0; s < 2; s++) row[2 * a + s] = beam[a][b] * scale[s];
        row[4] = bend[b] * bulge;
        if (turn != NULL)
            for (int t = 0; t < 3; t++) row[5 + t] = std[3] * turn[3 * b + t];
        else
            for (int c = 0; c < 2; c++) row[5 + c] = std[4] * (b == c ? 1.0 : 0.0);
    }
    if (cam < 0) return;
    /* _Screens.map_bases: the screen point's terms 1, x, y, xx, xy, yy times the map's std */
    const double *t = T + 3 * cam, *M = Rot + 9 * cam;
    double y[3] = {x[0] + t[0], x[1] + t[1], x[2] + t[2]}, xy[2];
    for (int j = 0; j < 2; j++)
        xy[j] = 2 * (y[0] * M[j] + y[1] * M[3 + j] + y[2] * M[6 + j]) / side[cam] - 1;
    double s = sigma[cam];
    double terms[6] = {s * 1.0, s * xy[0], s * xy[1], s * (xy[0] * xy[0]), s * (xy[0] * xy[1]),
                       s * (xy[1] * xy[1])};
    /* tracker._map_terms: each axis' eight coefficients as terms (-1: none, 0) */
    static const int pick[16] = {0, 1, 2, -1, -1, -1, 3, 4, -1, -1, -1, 0, 1, 2, 4, 5};
    for (int b = 0; b < 2; b++)
        for (int j = 0; j < 8; j++) {
            int term = pick[8 * b + j];
            block[b * width + width - 8 + j] = term < 0 ? 0.0 : terms[term];
        }
}

/* dot_moves(x, A, p0, q, across, shape, bend, turn, T, Rot, side, sigma, src, dst, out,
 *           cams, width, dir_std, offset_std, bulge_std, turn_std, residual_std):
 * each dot's block of moves (tracker._dot_moves), scattered as out[dst] = blocks[src]
 * (out zeroed by the caller). turn: empty where the cameras are unknown; cams: each dot's
 * camera index into T, Rot, side, sigma, or None where its map is not held. */
static PyObject *dot_moves(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[NBUF], *cams;
    static const int integer[NBUF] = {[12] = 1, [13] = 1};  /* src, dst */
    Py_ssize_t width;
    double std[5];
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOnddddd", &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12], &o[13],
                          &o[14], &cams, &width, &std[0], &std[1], &std[2], &std[3], &std[4])
        || !get_all(o, NBUF, integer, 14, &s))
        return NULL;
    PyObject *res = NULL, *fast = NULL;
    double *blocks = NULL;
    Py_ssize_t k = s.b[0].len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t ncam = s.b[10].len / (Py_ssize_t)sizeof(double);
    int turned = s.b[7].len > 0;
    Py_ssize_t places = s.b[12].len / (Py_ssize_t)sizeof(int64_t);
    if (!(sized(&s.b[0], 3 * k, "x") && sized(&s.b[1], 6 * k, "A") && sized(&s.b[2], 3, "p0")
          && sized(&s.b[3], 4, "q") && sized(&s.b[4], 6 * k, "across")
          && sized(&s.b[5], k, "shape") && sized(&s.b[6], 2 * k, "bend")
          && (!turned || sized(&s.b[7], 6 * k, "turn")) && sized(&s.b[8], 3 * ncam, "T")
          && sized(&s.b[9], 9 * ncam, "Rot") && sized(&s.b[11], ncam, "sigma")))
        goto done;
    if (s.b[13].len != s.b[12].len || width < (turned ? 8 : 7)) {
        PyErr_SetString(PyExc_ValueError, "laser kernel: src and dst differ or width too small");
        goto done;
    }
    fast = PySequence_Fast(cams, "laser kernel: cams must be a sequence");
    if (fast == NULL) goto done;
    if (PySequence_Fast_GET_SIZE(fast) != k) {
        PyErr_SetString(PyExc_ValueError, "laser kernel: one camera per dot");
        goto done;
    }
    Py_ssize_t nblock = k * 2 * width, nout = s.b[14].len / (Py_ssize_t)sizeof(double);
    blocks = calloc(nblock > 0 ? nblock : 1, sizeof(double));
    if (blocks == NULL) { PyErr_NoMemory(); goto done; }
    double R[9];
    quat_matrix(s.b[3].buf, R);
    const double *x = s.b[0].buf, *A = s.b[1].buf, *across = s.b[4].buf, *shape = s.b[5].buf;
    const double *bend = s.b[6].buf, *turn = turned ? s.b[7].buf : NULL;
    for (Py_ssize_t i = 0; i < k; i++) {
        PyObject *c = PySequence_Fast_GET_ITEM(fast, i);
        long cam = -1;
        if (c != Py_None) {
            cam = PyLong_AsLong(c);
            if (cam == -1 && PyErr_Occurred()) goto done;
            if (cam < 0 || cam >= ncam || width < (turned ? 16 : 15)) {
                PyErr_SetString(PyExc_ValueError, "laser kernel: camera index out of range");
                goto done;
            }
        }
        dot_block(x + 3 * i, A + 6 * i, s.b[2].buf, R, across + 6 * i, shape[i],
                  bend + 2 * i, turn ? turn + 6 * i : NULL, cam, s.b[8].buf, s.b[9].buf,
                  s.b[10].buf, s.b[11].buf, std, width, blocks + 2 * width * i);
    }
    const int64_t *src = s.b[12].buf, *dst = s.b[13].buf;
    double *out = s.b[14].buf;
    for (Py_ssize_t i = 0; i < places; i++) {
        if (src[i] < 0 || src[i] >= nblock || dst[i] < 0 || dst[i] >= nout) {
            PyErr_SetString(PyExc_ValueError, "laser kernel: a move's index out of range");
            goto done;
        }
        out[dst[i]] = blocks[src[i]];
    }
    res = Py_NewRef(Py_None);
done:
    Py_XDECREF(fast);
    free(blocks);
    release(&s);
    return res;
}

/* np.maximum and np.minimum of two doubles: NaN where either is NaN */
static double nan_max(double a, double b) { return isnan(a) || isnan(b) ? NAN : (a > b ? a : b); }
static double nan_min(double a, double b) { return isnan(a) || isnan(b) ? NAN : (a < b ? a : b); }

/* One dot's tracker._installation_covariances: its covariance (2 x 2) over its wall's axes
 * from the installation's tolerances, its bend slope (2) and, seen from an eye, its
 * camera-turn Jacobian (2 x 3). std: housing direction, housing offset, screen bulge,
 * camera turn, camera residual. */
static void dot_covariance(const double *x, const double *A, const double *p0, double shape,
                           const double *eye, const double *std, double *cov, double *slope,
                           double *turn) {
    const double *A0 = A, *A1 = A + 3;
    double n[3] = {A0[1] * A1[2] - A0[2] * A1[1], A0[2] * A1[0] - A0[0] * A1[2],
                   A0[0] * A1[1] - A0[1] * A1[0]};
    double d[3] = {x[0] - p0[0], x[1] - p0[1], x[2] - p0[2]};
    double r = sqrt(dot3(d, d));
    double dn = fabs(dot3(n, d));
    double c = nan_min(nan_max(dn / r, 0.05), 1.0);  /* cos(incidence) */
    double rd = r * std[0];
    double across = rd * rd + std[1] * std[1];
    double Ad[2] = {dot3(A0, d), dot3(A1, d)};
    double norm = sqrt(Ad[0] * Ad[0] + Ad[1] * Ad[1]);
    double u[2] = {1.0, 0.0};
    if (norm > 0) { u[0] = Ad[0] / norm; u[1] = Ad[1] / norm; }
    double stretch = 1 / (c * c) - 1;
    for (int a = 0; a < 2; a++)
        for (int b = 0; b < 2; b++)
            cov[2 * a + b] = across * ((a == b ? 1.0 : 0.0) + stretch * (u[a] * u[b]));
    double m = nan_max(dn, 0.05 * r);
    for (int b = 0; b < 2; b++) slope[b] = -Ad[b] / m;
    if (eye == NULL) {
        double v = std[4] * std[4];
        for (int a = 0; a < 2; a++)
            for (int b = 0; b < 2; b++) cov[2 * a + b] += v * (a == b ? 1.0 : 0.0);
    } else {
        double back[3] = {x[0] - eye[0], x[1] - eye[1], x[2] - eye[2]};
        double nb = dot3(n, back);
        double minus[3] = {-back[0], -back[1], -back[2]};
        for (int b = 0; b < 2; b++) slope[b] = slope[b] + dot3(A + 3 * b, minus) / fabs(nb);
        /* e_t x back for each world axis t, as tracker._TURNED and _TURNED_SIGN take it */
        double turned[3][3] = {{back[0] * 0.0, back[2] * -1.0, back[1] * 1.0},
                               {back[2] * 1.0, back[0] * 0.0, back[0] * -1.0},
                               {back[1] * -1.0, back[0] * 1.0, back[0] * 0.0}};
        for (int t = 0; t < 3; t++) {
            double towards = dot3(turned[t], n), moved[3];
            for (int i = 0; i < 3; i++) moved[i] = turned[t][i] - towards * back[i] / nb;
            for (int a = 0; a < 2; a++) turn[3 * a + t] = dot3(A + 3 * a, moved);
        }
        double v = std[3] * std[3];
        for (int a = 0; a < 2; a++)
            for (int b = 0; b < 2; b++)
                cov[2 * a + b] += v * dot3(turn + 3 * a, turn + 3 * b);
    }
    double bulge = std[2] * shape;
    for (int a = 0; a < 2; a++)
        for (int b = 0; b < 2; b++) cov[2 * a + b] = cov[2 * a + b] + bulge * bulge * (slope[a] * slope[b]);
}

/* installation_covariances(x, A, bend, eyes, p0, cov, slope, turn, dir_std, offset_std,
 *                          bulge_std, turn_std, residual_std): tracker._installation_covariances
 * of k dots into cov (k x 2 x 2), slope (k x 2) and, where eyes is not empty, turn
 * (k x 2 x 3); bend empty: a shape of 1; p0 one point (3) or one per dot (k x 3). */
static PyObject *installation_covariances(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[8];
    double std[5];
    if (!PyArg_ParseTuple(args, "OOOOOOOOddddd", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &std[0], &std[1], &std[2], &std[3], &std[4])
        || !get_all(o, 8, NULL, 5, &s))
        return NULL;
    Py_ssize_t k = s.b[0].len / (3 * (Py_ssize_t)sizeof(double));
    int bent = s.b[2].len > 0, seen = s.b[3].len > 0;
    int each = s.b[4].len != 3 * (Py_ssize_t)sizeof(double);
    PyObject *res = NULL;
    if (sized(&s.b[0], 3 * k, "x") && sized(&s.b[1], 6 * k, "A")
        && (!bent || sized(&s.b[2], k, "bend")) && (!seen || sized(&s.b[3], 3 * k, "eyes"))
        && (!each || sized(&s.b[4], 3 * k, "p0")) && sized(&s.b[5], 4 * k, "cov")
        && sized(&s.b[6], 2 * k, "slope") && sized(&s.b[7], seen ? 6 * k : 0, "turn")) {
        const double *x = s.b[0].buf, *A = s.b[1].buf, *bend = s.b[2].buf, *eyes = s.b[3].buf;
        const double *p0 = s.b[4].buf;
        double *cov = s.b[5].buf, *slope = s.b[6].buf, *turn = s.b[7].buf;
        for (Py_ssize_t i = 0; i < k; i++)
            dot_covariance(x + 3 * i, A + 6 * i, each ? p0 + 3 * i : p0, bent ? bend[i] : 1.0,
                           seen ? eyes + 3 * i : NULL, std, cov + 4 * i, slope + 2 * i,
                           seen ? turn + 6 * i : NULL);
        res = Py_NewRef(Py_None);
    }
    release(&s);
    return res;
}

/* kalman(idx, H, z, noise, cov, mean, S, gate) -> chi2: installation_estimate.py's
 * innovation of z (2,) = H (2 x k) theta[idx] + noise against the estimate (cov (M x M),
 * mean (M,)): its covariance H P H^T + noise into S (2 x 2) and its chi-square (NaN where S
 * is not positive definite or not finite); where that is <= gate, the update taken in place:
 * mean += P H^T S^-1 v, cov -= Y Y^T (Y = P H^T G, G G^T = S^-1, exactly symmetric). */
static PyObject *kalman(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[7];
    double gate;
    static const int integer[7] = {1, 0, 0, 0, 0, 0, 0};  /* idx */
    if (!PyArg_ParseTuple(args, "OOOOOOOd", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6],
                          &gate)
        || !get_all(o, 7, integer, 4, &s))
        return NULL;
    PyObject *res = NULL;
    double *PHt = NULL;
    Py_ssize_t M = s.b[5].len / (Py_ssize_t)sizeof(double);
    Py_ssize_t k = s.b[0].len / (Py_ssize_t)sizeof(int64_t);
    if (!(sized(&s.b[4], M * M, "cov") && sized(&s.b[1], 2 * k, "H") && sized(&s.b[2], 2, "z")
          && sized(&s.b[3], 4, "noise") && sized(&s.b[6], 4, "S")))
        goto done;
    double *P = s.b[4].buf, *mean = s.b[5].buf, *S = s.b[6].buf;
    const int64_t *idx = s.b[0].buf;
    const double *H = s.b[1].buf, *z = s.b[2].buf, *noise = s.b[3].buf;
    for (Py_ssize_t j = 0; j < k; j++)
        if (idx[j] < 0 || idx[j] >= M) {
            PyErr_SetString(PyExc_ValueError, "laser kernel: a state index out of range");
            goto done;
        }
    PHt = malloc(sizeof(double) * 2 * (M > 0 ? M : 1));
    if (PHt == NULL) { PyErr_NoMemory(); goto done; }
    double v[2];
    for (int c = 0; c < 2; c++) {
        double hm = 0.0;
        for (Py_ssize_t j = 0; j < k; j++) hm += H[c * k + j] * mean[idx[j]];
        v[c] = z[c] - hm;
    }
    for (Py_ssize_t i = 0; i < M; i++) {
        const double *row = P + i * M;
        double a0 = 0.0, a1 = 0.0;
        for (Py_ssize_t j = 0; j < k; j++) {
            double p = row[idx[j]];
            a0 += p * H[j];
            a1 += p * H[k + j];
        }
        PHt[2 * i] = a0;
        PHt[2 * i + 1] = a1;
    }
    for (int c = 0; c < 2; c++)
        for (int e = 0; e < 2; e++) {
            double acc = 0.0;
            for (Py_ssize_t j = 0; j < k; j++) acc += H[c * k + j] * PHt[2 * idx[j] + e];
            S[2 * c + e] = acc + noise[2 * c + e];
        }
    /* _covariance_inverse2 and _chi2 */
    double a = S[0], b = S[1], c = S[2], d = S[3], det = a * d - b * c;
    double chi2 = NAN, Si[4];
    if (a > 0.0 && det > 0.0 && isfinite(det)) {
        Si[0] = d / det; Si[1] = -b / det; Si[2] = -c / det; Si[3] = a / det;
        chi2 = (v[0] * Si[0] + v[1] * Si[2]) * v[0] + (v[0] * Si[1] + v[1] * Si[3]) * v[1];
    }
    if (chi2 <= gate) {
        /* mean += (P H^T S^-T) v; _root2 of S^-1; cov -= Y Y^T */
        double g00 = sqrt(Si[0]), g10 = 0.5 * (Si[1] + Si[2]) / g00;
        double rest = Si[3] - g10 * g10, g11 = sqrt(rest > 0.0 ? rest : 0.0);
        for (Py_ssize_t i = 0; i < M; i++) {
            double p0 = PHt[2 * i], p1 = PHt[2 * i + 1];
            double k0 = p0 * Si[0] + p1 * Si[1], k1 = p0 * Si[2] + p1 * Si[3];
            mean[i] += k0 * v[0] + k1 * v[1];
            PHt[2 * i] = p0 * g00 + p1 * g10;
            PHt[2 * i + 1] = p1 * g11;
        }
        for (Py_ssize_t i = 0; i < M; i++) {
            double y0 = PHt[2 * i], y1 = PHt[2 * i + 1];
            double *row = P + i * M;
            for (Py_ssize_t j = 0; j < M; j++) row[j] -= y0 * PHt[2 * j] + y1 * PHt[2 * j + 1];
        }
    }
    res = PyFloat_FromDouble(chi2);
done:
    free(PHt);
    release(&s);
    return res;
}

/* pose._rotations of one labeling: the rig's rotation (row-major) from the directions
 * P0 -> P1 (v1) and P0 -> P3 (v3); NaN throughout where they define no frame. */
static void rotation(const double *v1, const double *v3, double *R) {
    double n[3] = {v1[1] * v3[2] - v1[2] * v3[1], v1[2] * v3[0] - v1[0] * v3[2],
                   v1[0] * v3[1] - v1[1] * v3[0]};
    double len_v3 = norm3(v3), len_n = norm3(n);
    double x[3], z[3];
    for (int i = 0; i < 3; i++) {
        x[i] = -v3[i] / len_v3;
        z[i] = n[i] / len_n;
    }
    double y[3] = {z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]};
    int finite = 1;
    for (int i = 0; i < 3; i++) {
        R[3 * i] = x[i];
        R[3 * i + 1] = y[i];
        R[3 * i + 2] = z[i];
        finite &= isfinite(x[i]) && isfinite(y[i]) && isfinite(z[i]);
    }
    if (!finite || len_v3 < 1e-9 || len_n < 1e-12)
        for (int i = 0; i < 9; i++) R[i] = NAN;
}

/* The foot of P on the line through P1 along d12: P1 + lam d12, lam = (P - P1).d12 / d12.d12 */
static void foot(const double *P, const double *P1, const double *d12, double dd, double *out) {
    double w[3] = {P[0] - P1[0], P[1] - P1[1], P[2] - P1[2]};
    double lam = dot3(w, d12) / dd;
    for (int i = 0; i < 3; i++) out[i] = P1[i] + lam * d12[i];
}

/* frames(P, P0, R): pose.frames_from_points of m labeled hits P (m x 4 x 3) into P0 (m x 3)
 * and R (m x 3 x 3). */
static PyObject *frames(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2]) || !get_all(o, 3, NULL, 1, &s))
        return NULL;
    Py_ssize_t m = s.b[0].len / (12 * (Py_ssize_t)sizeof(double));
    PyObject *res = NULL;
    if (sized(&s.b[0], 12 * m, "P") && sized(&s.b[1], 3 * m, "P0") && sized(&s.b[2], 9 * m, "R")) {
        const double *P = s.b[0].buf;
        double *P0 = s.b[1].buf, *R = s.b[2].buf;
        for (Py_ssize_t j = 0; j < m; j++) {
            const double *P1 = P + 12 * j, *P2 = P1 + 3, *P3 = P1 + 6;
            double d12[3] = {P2[0] - P1[0], P2[1] - P1[1], P2[2] - P1[2]}, *p0 = P0 + 3 * j;
            foot(P3, P1, d12, dot3(d12, d12), p0);
            double v1[3] = {P1[0] - p0[0], P1[1] - p0[1], P1[2] - p0[2]};
            double v3[3] = {P3[0] - p0[0], P3[1] - p0[1], P3[2] - p0[2]};
            rotation(v1, v3, R + 9 * j);
        }
        res = Py_NewRef(Py_None);
    }
    release(&s);
    return res;
}

/* rotations(v1, v3, R): pose._rotations of m direction pairs (m x 3 each) into R (m x 3 x 3). */
static PyObject *rotations(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2]) || !get_all(o, 3, NULL, 2, &s))
        return NULL;
    Py_ssize_t m = s.b[0].len / (3 * (Py_ssize_t)sizeof(double));
    PyObject *res = NULL;
    if (sized(&s.b[0], 3 * m, "v1") && sized(&s.b[1], 3 * m, "v3") && sized(&s.b[2], 9 * m, "R")) {
        const double *v1 = s.b[0].buf, *v3 = s.b[1].buf;
        for (Py_ssize_t j = 0; j < m; j++) rotation(v1 + 3 * j, v3 + 3 * j, (double *)s.b[2].buf + 9 * j);
        res = Py_NewRef(Py_None);
    }
    release(&s);
    return res;
}

/* labelings(points, perms, eps, P0, rays): pose._labelings of four points (4 x 3) under the
 * labelings perms (L x 4, the point labeled each diode): eq. 5.6's eps of each (inf where
 * not finite), its P0 (L x 3) and its rays from P0 to the points labeled diodes 1..4
 * (L x 4 x 3). */
static PyObject *labelings(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 0};
    PyObject *o[5];
    static const int integer[5] = {0, 1, 0, 0, 0};
    /* eq. 5.7's pairs that must be perpendicular: beam 4 with 1, 2, 3; beam 3 with 1, 2 */
    static const int pa[5] = {3, 3, 3, 0, 1}, pb[5] = {0, 1, 2, 2, 2};
    if (!PyArg_ParseTuple(args, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4])
        || !get_all(o, 5, integer, 2, &s))
        return NULL;
    Py_ssize_t L = s.b[1].len / (4 * (Py_ssize_t)sizeof(int64_t));
    PyObject *res = NULL;
    if (sized(&s.b[0], 12, "points") && sized(&s.b[2], L, "eps") && sized(&s.b[3], 3 * L, "P0")
        && sized(&s.b[4], 12 * L, "rays")) {
        const double *pts = s.b[0].buf;
        const int64_t *perms = s.b[1].buf;
        double *eps = s.b[2].buf, *P0 = s.b[3].buf, *rays = s.b[4].buf;
        for (Py_ssize_t i = 0; i < L; i++) {
            const double *P[4];
            for (int k = 0; k < 4; k++) {
                int64_t j = perms[4 * i + k];
                if (j < 0 || j > 3) {
                    PyErr_SetString(PyExc_ValueError, "laser kernel: a labeling's point out of range");
                    goto done;
                }
                P[k] = pts + 3 * j;
            }
            double d12[3] = {P[1][0] - P[0][0], P[1][1] - P[0][1], P[1][2] - P[0][2]};
            double dd = dot3(d12, d12), *p0 = P0 + 3 * i, other[3], *r = rays + 12 * i, u[4][3];
            foot(P[2], P[0], d12, dd, p0);     /* P0, eq. 5.6's frame */
            foot(P[3], P[0], d12, dd, other);  /* P0', eq. 5.8 */
            for (int k = 0; k < 4; k++) {
                for (int c = 0; c < 3; c++) r[3 * k + c] = P[k][c] - p0[c];
                double len = norm3(r + 3 * k);
                for (int c = 0; c < 3; c++) u[k][c] = r[3 * k + c] / len;
            }
            double perp = 0.0;
            for (int q = 0; q < 5; q++) perp += fabs(dot3(u[pa[q]], u[pb[q]]));
            double apart[3] = {p0[0] - other[0], p0[1] - other[1], p0[2] - other[2]};
            const double *a = r, *b = r + 6;
            double n[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                           a[0] * b[1] - a[1] * b[0]};
            double e = perp + dot3(apart, apart) + (dot3(n, r + 9) <= 0 ? 1.0 : 0.0);
            eps[i] = isfinite(e) ? e : INFINITY;
        }
        res = Py_NewRef(Py_None);
    }
done:
    release(&s);
    return res;
}

static PyMethodDef methods[] = {
    {"labelings", labelings, METH_VARARGS,
     "Eq. 5.6's eps of every labeling of four points, their P0 and rays (pose._labelings)."},
    {"frames", frames, METH_VARARGS,
     "The rig frames of labeled hits (pose.frames_from_points), into P0 and R."},
    {"rotations", rotations, METH_VARARGS,
     "The rig rotations from P0's directions to P1 and P3 (pose._rotations), into R."},
    {"dot_moves", dot_moves, METH_VARARGS,
     "Each dot's moves per installation parameter (tracker._dot_moves), into out."},
    {"installation_covariances", installation_covariances, METH_VARARGS,
     "Each dot's installation covariance and slopes (tracker._installation_covariances), into "
     "the given arrays."},
    {"kalman", kalman, METH_VARARGS,
     "The installation estimate's innovation chi-square, its update taken in place if gated in."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void) { return uma_twin_module(&module); }
