/* The compiled twin of the fiducial tracker's per-frame arithmetic on small arrays:
 * pose.py's fits (the reprojection residuals and Jacobian of a stack of poses) and
 * gauss_newton (their undamped Gauss-Newton steps); edges.py's profile crossings (each
 * profile's rising crossing of its level nearest the centre), side lines' fits, the pixel
 * locking's share of their scatter and its line gains, and the corners' covariance; border.py's crossing_bias (the modelled profiles across thin sides
 * and their crossings).
 *
 * The same arithmetic as the numpy code: the Jacobian in the decoupled [position,
 * camera-frame rotation] form, the step's 6 x 6 normal equations solved by LU with
 * partial pivoting (LAPACK's gesv, which numpy's solve calls, does the same; a singular
 * system takes no step, as services.linalg.solve_stack), the rotation stepped by
 * Rodrigues' formula as pose.exp_rotation.  The fits' sums run in another order than
 * numpy's matrix products, so they agree to rounding (about 1e-15 relative), not to the
 * bit; the edge crossings are the numpy code's operations on the same numbers and agree to
 * the bit (compiled without floating-point contraction); the modelled profiles' CDFs take
 * the C library's tanh, numpy's may round differently, to about 1e-16.  Why compiled: in
 * numpy a frame's ten tags spend about 0.4 ms in some hundred calls on a few hundred
 * numbers, the interpreter's cost rather than the arithmetic's.  Optional: when this does not build, pose.py, edges.py and border.py run
 * in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <string.h>

/* Residuals (observed - projected, 2n) and Jacobian (2n x 6, row-major) of n object points
 * obj (n x 3) at pose (R row-major, t) seen at ideal pixels img (n x 2); K = fx, fy, cx, cy. */
static void fit_one(Py_ssize_t n, const double *obj, const double *img, const double *K,
                    const double *R, const double *t, double *res, double *J) {
    for (Py_ssize_t p = 0; p < n; p++) {
        const double *o = obj + 3 * p;
        double q[3];
        for (int i = 0; i < 3; i++) q[i] = R[3 * i] * o[0] + R[3 * i + 1] * o[1] + R[3 * i + 2] * o[2];
        double iz = 1.0 / (q[2] + t[2]);
        double xn = (q[0] + t[0]) * iz, yn = (q[1] + t[1]) * iz;
        res[2 * p] = img[2 * p] - (K[0] * xn + K[2]);
        res[2 * p + 1] = img[2 * p + 1] - (K[1] * yn + K[3]);
        double a = K[0] * iz, b = K[1] * iz, c = -xn * a, d = -yn * b;
        double *u = J + 12 * p, *v = u + 6;
        u[0] = a; u[1] = 0.0; u[2] = c;
        u[3] = q[1] * c; u[4] = q[2] * a - q[0] * c; u[5] = -q[1] * a;
        v[0] = 0.0; v[1] = b; v[2] = d;
        v[3] = q[1] * d - q[2] * b; v[4] = -q[0] * d; v[5] = q[0] * b;
    }
}

/* x = A^-1 b for a 6 x 6 system by LU with partial pivoting (the first largest pivot, as
 * LAPACK's idamax picks); 0 where a pivot is exactly zero (singular). A and b are
 * overwritten. */
static int solve6(double A[36], double b[6], double x[6]) {
    for (int k = 0; k < 6; k++) {
        int p = k;
        for (int i = k + 1; i < 6; i++)
            if (fabs(A[6 * i + k]) > fabs(A[6 * p + k])) p = i;
        if (A[6 * p + k] == 0.0 || isnan(A[6 * p + k])) return 0;
        if (p != k) {
            for (int j = 0; j < 6; j++) {
                double s = A[6 * k + j]; A[6 * k + j] = A[6 * p + j]; A[6 * p + j] = s;
            }
            double s = b[k]; b[k] = b[p]; b[p] = s;
        }
        double inv = 1.0 / A[6 * k + k];
        for (int i = k + 1; i < 6; i++) {
            double l = A[6 * i + k] * inv;
            for (int j = k + 1; j < 6; j++) A[6 * i + j] -= l * A[6 * k + j];
            b[i] -= l * b[k];
        }
    }
    for (int i = 5; i >= 0; i--) {
        double s = b[i];
        for (int j = i + 1; j < 6; j++) s -= A[6 * i + j] * x[j];
        x[i] = s / A[6 * i + i];
    }
    return 1;
}

/* pose.exp_rotation of one rotation vector: I + sin(th)/th W + (1 - cos th)/th^2 (phi phi^T - th^2 I) */
static void exp_rotation(const double phi[3], double E[9]) {
    double theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2];
    double theta = sqrt(theta2);
    double half = theta == 0.0 ? 1.0 : sin(theta / 2) / (theta / 2);
    double a = half * cos(theta / 2), b = half * half / 2;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) E[3 * i + j] = b * (phi[i] * phi[j]);
    for (int i = 0; i < 3; i++) E[4 * i] += 1 - b * theta2;
    E[3] += a * phi[2]; E[1] -= a * phi[2];
    E[2] += a * phi[1]; E[6] -= a * phi[1];
    E[7] += a * phi[0]; E[5] -= a * phi[0];
}

typedef struct {
    Py_buffer b[9];
    int n;
} buffers_t;

static void release(buffers_t *bufs) {
    for (int i = 0; i < bufs->n; i++) PyBuffer_Release(&bufs->b[i]);
}

/* The stack's sizes (poses m, points n) from its buffers, checked; -1 (error set) if they
 * do not agree. */
static Py_ssize_t stack_points(const buffers_t *s, Py_ssize_t *m) {
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    *m = s->b[3].len / (9 * d);
    if (*m <= 0 || s->b[3].len != *m * 9 * d || s->b[4].len != *m * 3 * d
        || s->b[2].len != 4 * d || s->b[0].len % (*m * 3 * d) != 0) {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent stack sizes");
        return -1;
    }
    Py_ssize_t n = s->b[0].len / (*m * 3 * d);
    if (s->b[1].len != *m * n * 2 * d || s->b[5].len != *m * n * 2 * d
        || s->b[6].len != *m * n * 12 * d) {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent stack sizes");
        return -1;
    }
    return n;
}

/* fits(obj, img, K, R, t, res, J): residuals and Jacobians of a stack of poses. */
static PyObject *fits(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 7};
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*w*", &s.b[0], &s.b[1], &s.b[2], &s.b[3], &s.b[4],
                          &s.b[5], &s.b[6]))
        return NULL;
    Py_ssize_t m, n = stack_points(&s, &m);
    if (n >= 0) {
        const double *obj = s.b[0].buf, *img = s.b[1].buf, *K = s.b[2].buf;
        const double *R = s.b[3].buf, *t = s.b[4].buf;
        double *res = s.b[5].buf, *J = s.b[6].buf;
        for (Py_ssize_t i = 0; i < m; i++)
            fit_one(n, obj + 3 * n * i, img + 2 * n * i, K, R + 9 * i, t + 3 * i,
                    res + 2 * n * i, J + 12 * n * i);
    }
    release(&s);
    if (n < 0) return NULL;
    Py_RETURN_NONE;
}

/* gauss_newton(obj, img, K, R, t, res, J, turned, steps): R and t stepped in place, the
 * fits at the last poses in res and J, how far (rad) the last step turned each. */
static PyObject *gauss_newton(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 8};
    int steps;
    if (!PyArg_ParseTuple(args, "y*y*y*w*w*w*w*w*i", &s.b[0], &s.b[1], &s.b[2], &s.b[3],
                          &s.b[4], &s.b[5], &s.b[6], &s.b[7], &steps))
        return NULL;
    Py_ssize_t m, n = stack_points(&s, &m);
    if (n >= 0 && s.b[7].len != m * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent stack sizes");
        n = -1;
    }
    if (n >= 0) {
        const double *obj = s.b[0].buf, *img = s.b[1].buf, *K = s.b[2].buf;
        double *R = s.b[3].buf, *t = s.b[4].buf, *res = s.b[5].buf, *J = s.b[6].buf;
        double *turned = s.b[7].buf;
        for (Py_ssize_t i = 0; i < m; i++) {
            const double *o = obj + 3 * n * i, *im = img + 2 * n * i;
            double *Ri = R + 9 * i, *ti = t + 3 * i, *r = res + 2 * n * i, *Ji = J + 12 * n * i;
            fit_one(n, o, im, K, Ri, ti, r, Ji);
            turned[i] = 0.0;
            for (int step = 0; step < steps; step++) {
                double A[36] = {0}, g[6] = {0}, delta[6] = {0}, E[9], Rn[9];
                for (Py_ssize_t k = 0; k < 2 * n; k++) {
                    const double *row = Ji + 6 * k;
                    for (int a = 0; a < 6; a++) {
                        g[a] += row[a] * r[k];
                        for (int c = 0; c < 6; c++) A[6 * a + c] += row[a] * row[c];
                    }
                }
                if (!solve6(A, g, delta)) memset(delta, 0, sizeof delta);
                turned[i] = sqrt(delta[3] * delta[3] + delta[4] * delta[4] + delta[5] * delta[5]);
                exp_rotation(delta + 3, E);
                for (int a = 0; a < 3; a++)
                    for (int c = 0; c < 3; c++)
                        Rn[3 * a + c] = E[3 * a] * Ri[c] + E[3 * a + 1] * Ri[3 + c]
                                        + E[3 * a + 2] * Ri[6 + c];
                memcpy(Ri, Rn, sizeof Rn);
                for (int a = 0; a < 3; a++) ti[a] += delta[a];
                fit_one(n, o, im, K, Ri, ti, r, Ji);
            }
        }
    }
    release(&s);
    if (n < 0) return NULL;
    Py_RETURN_NONE;
}

/* crossings(profile, level, offsets, out): per profile (its samples at offsets), where it
 * first rises through its level nearest offset 0, linearly between samples; inf if never. */
static PyObject *crossings(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 4};
    if (!PyArg_ParseTuple(args, "y*y*y*w*", &s.b[0], &s.b[1], &s.b[2], &s.b[3])) return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    Py_ssize_t count = s.b[1].len / d, steps = s.b[2].len / d;
    int ok = steps >= 2 && s.b[0].len == count * steps * d && s.b[3].len == count * d;
    if (ok) {
        const double *profile = s.b[0].buf, *level = s.b[1].buf, *offs = s.b[2].buf;
        double *out = s.b[3].buf, spacing = offs[1] - offs[0];
        for (Py_ssize_t p = 0; p < count; p++) {
            const double *x = profile + steps * p;
            double best = INFINITY, best_abs = INFINITY;
            for (Py_ssize_t j = 0; j + 1 < steps; j++) {
                double lo = x[j] - level[p], hi = x[j + 1] - level[p];
                if (lo < 0 && hi >= 0) {
                    double w = offs[j] + lo / (lo - hi) * spacing;
                    if (fabs(w) < best_abs) {
                        best_abs = fabs(w);
                        best = w;
                    }
                }
            }
            out[p] = best;
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent profile sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* moved(R, t, delta, R_out, t_out): pose.py's _moved, a stack of poses (R (m, 3, 3), t
 * (m, 3)) stepped by delta (m, 6) [position, rotation]: exp(phi) R, t + dp. */
static PyObject *moved(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 5};
    if (!PyArg_ParseTuple(args, "y*y*y*w*w*", &s.b[0], &s.b[1], &s.b[2], &s.b[3], &s.b[4]))
        return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double), m = s.b[1].len / (3 * d);
    int ok = s.b[0].len == 9 * m * d && s.b[1].len == 3 * m * d && s.b[2].len == 6 * m * d
             && s.b[3].len == s.b[0].len && s.b[4].len == s.b[1].len;
    if (ok) {
        const double *R = s.b[0].buf, *t = s.b[1].buf, *delta = s.b[2].buf;
        double *R_out = s.b[3].buf, *t_out = s.b[4].buf;
        for (Py_ssize_t i = 0; i < m; i++) {
            double E[9];
            const double *Ri = R + 9 * i, *di = delta + 6 * i;
            exp_rotation(di + 3, E);
            for (int a = 0; a < 3; a++) {
                for (int c = 0; c < 3; c++)
                    R_out[9 * i + 3 * a + c] = E[3 * a] * Ri[c] + E[3 * a + 1] * Ri[3 + c]
                                               + E[3 * a + 2] * Ri[6 + c];
                t_out[3 * i + a] = t[3 * i + a] + di[a];
            }
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent stack sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* lines(points, w, mean, dev, direction): per side (its k weighted points, x y), edges.py's
 * _lines: the weighted mean, the points' deviations from it, the principal axis. */
static PyObject *lines(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 5};
    if (!PyArg_ParseTuple(args, "y*y*w*w*w*", &s.b[0], &s.b[1], &s.b[2], &s.b[3], &s.b[4]))
        return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    Py_ssize_t sides = s.b[2].len / (2 * d), k = sides > 0 ? s.b[1].len / (sides * d) : 0;
    int ok = sides > 0 && s.b[2].len == sides * 2 * d && s.b[4].len == sides * 2 * d
             && s.b[1].len == sides * k * d && s.b[0].len == sides * k * 2 * d
             && s.b[3].len == s.b[0].len;
    if (ok) {
        const double *points = s.b[0].buf, *w = s.b[1].buf;
        double *mean = s.b[2].buf, *dev = s.b[3].buf, *direction = s.b[4].buf;
        for (Py_ssize_t i = 0; i < sides; i++) {
            const double *p = points + 2 * k * i, *wi = w + k * i;
            double *di = dev + 2 * k * i;
            double total = 0.0, sx = 0.0, sy = 0.0, cxx = 0.0, cyy = 0.0, cxy = 0.0;
            for (Py_ssize_t j = 0; j < k; j++) {
                total += wi[j];
                sx += wi[j] * p[2 * j];
                sy += wi[j] * p[2 * j + 1];
            }
            double scale = total > 1.0 ? total : 1.0;
            double mx = sx / scale, my = sy / scale;
            for (Py_ssize_t j = 0; j < k; j++) {
                double dx = p[2 * j] - mx, dy = p[2 * j + 1] - my;
                di[2 * j] = dx;
                di[2 * j + 1] = dy;
                cxx += wi[j] * dx * dx;
                cyy += wi[j] * dy * dy;
                cxy += wi[j] * dx * dy;
            }
            double theta = 0.5 * atan2(2 * cxy, cxx - cyy);
            mean[2 * i] = mx;
            mean[2 * i + 1] = my;
            direction[2 * i] = cos(theta);
            direction[2 * i + 1] = sin(theta);
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent line sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* corner_covariance(corners, point, direction, dev, w, few, taken, fallback_std, out): per
 * marker (4 sides of k edge points), edges.py's _corner_covariance: the corners' joint
 * covariance (8 x 8) from the four lines' fits (their pooled scatter less the locking's
 * share and dof, taken), each line off by a at its points' mean and turned by b, corner c
 * moved by sides c - 1 and c through the inverse of their normals. */
static PyObject *corner_covariance(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 8};
    double fallback;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*dw*", &s.b[0], &s.b[1], &s.b[2], &s.b[3],
                          &s.b[4], &s.b[5], &s.b[6], &fallback, &s.b[7]))
        return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    Py_ssize_t n = s.b[7].len / (64 * d), k = n > 0 ? s.b[4].len / (4 * n * d) : 0;
    int ok = n > 0 && s.b[7].len == n * 64 * d && s.b[0].len == n * 8 * d
             && s.b[1].len == n * 8 * d && s.b[2].len == n * 8 * d && s.b[5].len == n * 4
             && s.b[4].len == n * 4 * k * d && s.b[3].len == n * 8 * k * d
             && s.b[6].len == n * 8 * d;
    if (ok) {
        static const int prev[4] = {3, 0, 1, 2}, next[4] = {1, 2, 3, 0};
        const double *corners = s.b[0].buf, *point = s.b[1].buf, *direction = s.b[2].buf;
        const double *dev = s.b[3].buf, *w = s.b[4].buf;
        const unsigned char *few = s.b[5].buf;
        const double *taken = s.b[6].buf;
        double *out = s.b[7].buf, fallback2 = fallback * fallback;
        for (Py_ssize_t m = 0; m < n; m++) {
            const double *c = corners + 8 * m, *pt = point + 8 * m, *dir = direction + 8 * m;
            const unsigned char *f = few + 4 * m;
            double normal[8], count[4], s_uu[4], u_near[4], u_far[4], middle[4];
            double var[8], G[64], rss = 0.0, dof = 0.0;
            for (int e = 0; e < 4; e++) {
                normal[2 * e] = -dir[2 * e + 1];
                normal[2 * e + 1] = dir[2 * e];
                const double *dv = dev + 2 * k * (4 * m + e), *we = w + k * (4 * m + e);
                double total = 0.0, cross = 0.0, length2 = 0.0;
                for (Py_ssize_t j = 0; j < k; j++) {
                    double across = dv[2 * j] * normal[2 * e] + dv[2 * j + 1] * normal[2 * e + 1];
                    double along = dv[2 * j] * dir[2 * e] + dv[2 * j + 1] * dir[2 * e + 1];
                    total += we[j];
                    cross += we[j] * (across * across);
                    length2 += we[j] * (along * along);
                }
                count[e] = total;
                s_uu[e] = length2 > 1e-12 ? length2 : 1e-12;
                if (!f[e]) {
                    const double *tk = taken + 2 * (4 * m + e);
                    rss += cross - tk[0];
                    dof += (total - 2 > 0 ? total - 2 : 0) - tk[1];
                }
            }
            double s2 = dof > 0 ? rss / (dof > 1 ? dof : 1) : fallback2;
            for (int e = 0; e < 4; e++) {
                const double *pp = pt + 2 * prev[e], *dp = dir + 2 * prev[e];
                u_near[e] = (c[2 * e] - pt[2 * e]) * dir[2 * e]
                            + (c[2 * e + 1] - pt[2 * e + 1]) * dir[2 * e + 1];
                u_far[e] = (c[2 * e] - pp[0]) * dp[0] + (c[2 * e + 1] - pp[1]) * dp[1];
            }
            for (int e = 0; e < 4; e++) {
                double length = fabs(u_far[next[e]] - u_near[e]);
                middle[e] = f[e] ? (u_far[next[e]] + u_near[e]) / 2 : 0.0;
                double least = length > 1e-6 ? length : 1e-6;
                var[2 * e] = f[e] ? fallback2 / 2 : s2 / (count[e] > 1 ? count[e] : 1);
                var[2 * e + 1] = f[e] ? 2 * fallback2 / (least * least) : s2 / s_uu[e];
            }
            memset(G, 0, sizeof G);
            for (int e = 0; e < 4; e++) {
                /* the inverse of [[normal of side e - 1], [normal of side e]] */
                const double *a = normal + 2 * prev[e], *b = normal + 2 * e;
                double det = a[0] * b[1] - a[1] * b[0];
                double inv[4] = {b[1] / det, -a[1] / det, -b[0] / det, a[0] / det};
                for (int xy = 0; xy < 2; xy++) {
                    double *row = G + 8 * (2 * e + xy);
                    row[2 * prev[e]] = inv[2 * xy];
                    row[2 * prev[e] + 1] = inv[2 * xy] * (u_far[e] - middle[prev[e]]);
                    row[2 * e] = inv[2 * xy + 1];
                    row[2 * e + 1] = inv[2 * xy + 1] * (u_near[e] - middle[e]);
                }
            }
            double *cov = out + 64 * m;
            for (int r = 0; r < 8; r++)
                for (int q = 0; q < 8; q++) {
                    double sum = 0.0;
                    for (int j = 0; j < 8; j++) sum += G[8 * r + j] * var[j] * G[8 * q + j];
                    cov[8 * r + q] = sum;
                }
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent covariance sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* code_crossings(rows, along, along_step, width, offsets, own, sigma, page_a, page_b, out):
 * border.py's crossing_bias once each point's place is known.  Per side u (of a tag whose
 * code rows behind it are rows (u, R, m), 1 white) and point k along it: each code row's
 * white share at the point (the row's cells blended along the side by the blur: its
 * position along (u, k, R) in cells, px per cell along_step (u, k, R); beyond the row's
 * ends the white margin), for the tag's code (v = 0) and an average one (v = 1: half
 * white between the border's black cells); the blurred print across the side at the
 * side's offsets (u, I) px outwards: the margin's normal CDF plus each row's share times
 * its band's, the border cells width (u, k) px wide; then the profile's crossing of its
 * own middle (where own, (u) bytes) or of 0.5, nearest the middle, linear between
 * samples, 0 where none: out (2, u, k).  The CDF is Page's tanh form, border.normal_cdf's:
 * 0.5 + 0.5 tanh(z (a + b z z)). */
static double page_cdf(double z, double a, double b) {
    return 0.5 + 0.5 * tanh(z * (a + b * z * z));
}

#define MAX_ROWS 8
#define MAX_CELLS 64
#define MAX_STEPS 64

static PyObject *code_crossings(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 7};
    double sigma, pa, pb;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*dddw*", &s.b[0], &s.b[1], &s.b[2], &s.b[3],
                          &s.b[4], &s.b[5], &sigma, &pa, &pb, &s.b[6]))
        return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    Py_ssize_t u = s.b[5].len, k = u > 0 ? s.b[3].len / (u * d) : 0;
    Py_ssize_t steps = u > 0 ? s.b[4].len / (u * d) : 0;
    Py_ssize_t rows = u > 0 && k > 0 ? s.b[1].len / (u * k * d) : 0;
    Py_ssize_t m = u > 0 && rows > 0 ? s.b[0].len / (u * rows * d) : 0;
    int ok = u > 0 && k > 0 && steps >= 2 && steps <= MAX_STEPS && rows >= 1
             && rows <= MAX_ROWS && m >= 3 && m <= MAX_CELLS
             && s.b[0].len == u * rows * m * d && s.b[1].len == u * k * rows * d
             && s.b[2].len == s.b[1].len && s.b[3].len == u * k * d
             && s.b[4].len == u * steps * d && s.b[6].len == 2 * u * k * d;
    if (ok) {
        const double *code = s.b[0].buf, *along = s.b[1].buf, *along_step = s.b[2].buf;
        const double *width = s.b[3].buf, *offsets = s.b[4].buf;
        const unsigned char *own = s.b[5].buf;
        double *out = s.b[6].buf;
        for (Py_ssize_t side = 0; side < u; side++) {
            const double *at = offsets + steps * side;
            for (Py_ssize_t j = 0; j < k; j++) {
                double white[2][MAX_ROWS], band[MAX_ROWS + 1][MAX_STEPS], margin[MAX_STEPS];
                for (Py_ssize_t r = 0; r < rows; r++) {
                    const double *cells = code + (side * rows + r) * m;
                    Py_ssize_t p = (side * k + j) * rows + r;
                    double scale = along_step[p] / sigma, edge[MAX_CELLS + 1];
                    for (Py_ssize_t c = 0; c <= m; c++)
                        edge[c] = page_cdf(((double)c - along[p]) * scale, pa, pb);
                    double coded = 0.0, average = 0.0;
                    for (Py_ssize_t c = 0; c < m; c++) {
                        double share = edge[c + 1] - edge[c];
                        coded += cells[c] * share;
                        average += (c > 0 && c < m - 1 ? 0.5 : 0.0) * share;
                    }
                    double beyond = edge[0] + 1 - edge[m];
                    white[0][r] = coded + beyond;
                    white[1][r] = average + beyond;
                }
                double w = width[side * k + j];
                for (Py_ssize_t t = 0; t < steps; t++) {
                    margin[t] = page_cdf(at[t] / sigma, pa, pb);
                    for (Py_ssize_t r = 0; r <= rows; r++)
                        band[r][t] = page_cdf((at[t] + (double)(r + 1) * w) / sigma, pa, pb);
                }
                for (int v = 0; v < 2; v++) {
                    double profile[MAX_STEPS], lowest = INFINITY, highest = -INFINITY;
                    Py_ssize_t centre = steps / 2;
                    for (Py_ssize_t t = 0; t < steps; t++) {
                        double sum = white[v][0] * (band[1][t] - band[0][t]);
                        for (Py_ssize_t r = 1; r < rows; r++)
                            sum += white[v][r] * (band[r + 1][t] - band[r][t]);
                        profile[t] = margin[t] + sum;
                        if (t <= centre && profile[t] < lowest) lowest = profile[t];
                        if (t >= centre && profile[t] > highest) highest = profile[t];
                    }
                    double level = own[side] ? (lowest + highest) / 2 : 0.5;
                    double best = INFINITY, best_abs = INFINITY;
                    for (Py_ssize_t t = 0; t + 1 < steps; t++) {
                        double lo = profile[t] - level, hi = profile[t + 1] - level;
                        if (lo < 0 && hi >= 0) {
                            double x = at[t] + lo / (lo - hi) * (at[t + 1] - at[t]);
                            if (fabs(x) < best_abs) {
                                best_abs = fabs(x);
                                best = x;
                            }
                        }
                    }
                    out[(v * u + side) * k + j] = isfinite(best) ? best : 0.0;
                }
            }
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent profile model sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* locking_terms(edge, dev, direction, w, corners, fade_deg, fade, fit_points, sweep_px,
 * taken, gains): per side (k weighted points), edges.py's _locking_terms: the share of the
 * points' squared scatter across their line that a sine and a cosine of their phase on the
 * pixel grid explain beyond the line's offset and turn, with its 2 dof (where the side has
 * fit_points or more points sweeping sweep_px or more across the axis nearer its normal;
 * else zeros), and how far a unit locking moves its line (the offset at the points' mean,
 * the turn at the side's ends), faded by the side's angle to that axis (fade_deg, fade:
 * np.interp's table). */
static PyObject *locking_terms(PyObject *self, PyObject *args) {
    buffers_t s = {.n = 9};
    double fit_points, sweep_px;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*ddw*w*", &s.b[0], &s.b[1], &s.b[2], &s.b[3],
                          &s.b[4], &s.b[5], &s.b[6], &fit_points, &sweep_px, &s.b[7],
                          &s.b[8]))
        return NULL;
    Py_ssize_t d = (Py_ssize_t)sizeof(double);
    Py_ssize_t sides = s.b[2].len / (2 * d), k = sides > 0 ? s.b[3].len / (sides * d) : 0;
    Py_ssize_t nf = s.b[5].len / d;
    int ok = sides > 0 && sides % 4 == 0 && s.b[2].len == sides * 2 * d
             && s.b[3].len == sides * k * d && s.b[0].len == sides * k * 2 * d
             && s.b[1].len == s.b[0].len && s.b[4].len == sides * 2 * d && nf > 0
             && s.b[6].len == nf * d && s.b[7].len == sides * 2 * d
             && s.b[8].len == sides * 2 * d;
    if (ok) {
        const double *edge = s.b[0].buf, *dev = s.b[1].buf, *direction = s.b[2].buf;
        const double *w = s.b[3].buf, *corners = s.b[4].buf, *fdeg = s.b[5].buf;
        const double *fval = s.b[6].buf;
        double *taken = s.b[7].buf, *gains = s.b[8].buf;
        const double two_pi = 2 * M_PI;
        for (Py_ssize_t i = 0; i < sides; i++) {
            const double *e = edge + 2 * k * i, *dv = dev + 2 * k * i, *wi = w + k * i;
            const double dx = direction[2 * i], dy = direction[2 * i + 1];
            const int axis = fabs(dx) >= fabs(dy) ? 1 : 0;  /* the normal's larger part */
            const double nx = -dy, ny = dx;
            double count = 0.0, suu = 0.0, hi = -INFINITY, lo = -INFINITY;
            double ws = 0.0, wc = 0.0;
            for (Py_ssize_t j = 0; j < k; j++) {
                double u = dv[2 * j] * dx + dv[2 * j + 1] * dy;
                double ph = two_pi * e[2 * j + axis];
                count += wi[j];
                suu += wi[j] * u * u;
                ws += wi[j] * sin(ph);
                wc += wi[j] * cos(ph);
                if (wi[j] > 0) {
                    if (u > hi) hi = u;
                    if (-u > lo) lo = -u;
                }
            }
            double scale = count > 1.0 ? count : 1.0, spread = suu > 1e-12 ? suu : 1e-12;
            double ms = ws / scale, mc = wc / scale;
            /* the sine and cosine less their straight-line fit along the side */
            double us = 0.0, uc = 0.0;
            for (Py_ssize_t j = 0; j < k; j++) {
                double u = dv[2 * j] * dx + dv[2 * j + 1] * dy;
                double ph = two_pi * e[2 * j + axis];
                us += wi[j] * u * (sin(ph) - ms);
                uc += wi[j] * u * (cos(ph) - mc);
            }
            double bs = us / spread, bc = uc / spread;
            double ss = 0.0, sc = 0.0, cc = 0.0, sr = 0.0, cr = 0.0;
            for (Py_ssize_t j = 0; j < k; j++) {
                double u = dv[2 * j] * dx + dv[2 * j + 1] * dy;
                double across = dv[2 * j] * nx + dv[2 * j + 1] * ny;
                double ph = two_pi * e[2 * j + axis];
                double sj = sin(ph) - ms - bs * u, cj = cos(ph) - mc - bc * u;
                ss += wi[j] * sj * sj;
                sc += wi[j] * sj * cj;
                cc += wi[j] * cj * cj;
                sr += wi[j] * sj * across;
                cr += wi[j] * cj * across;
            }
            double extent = hi + lo, det = ss * cc - sc * sc;
            double sweep = (extent > 0 ? extent : 0.0) * fabs(axis ? dy : dx);
            int use = count >= fit_points && sweep >= sweep_px && det > 1e-6 * scale * scale;
            taken[2 * i] = use ? (cc * sr * sr - 2 * sc * sr * cr + ss * cr * cr) / det : 0.0;
            taken[2 * i + 1] = use ? 2.0 : 0.0;
            /* the gains: |mean exp(2 pi i x)| and its line's slope at the side's ends */
            const double *c0 = corners + 2 * i;
            const double *c1 = corners + 2 * ((i % 4 == 3) ? i - 3 : i + 1);
            double half = hypot(c1[0] - c0[0], c1[1] - c0[1]) / 2;
            double along = fabs(dx) > fabs(dy) ? fabs(dx) : fabs(dy);
            double angle = acos(along < 1.0 ? (along > 0.0 ? along : 0.0) : 1.0) * 180.0 / M_PI;
            double f = fval[nf - 1];
            if (angle <= fdeg[0]) f = fval[0];
            else
                for (Py_ssize_t q = 1; q < nf; q++)
                    if (angle <= fdeg[q]) {
                        f = fval[q - 1] + (fval[q] - fval[q - 1]) * (angle - fdeg[q - 1])
                                              / (fdeg[q] - fdeg[q - 1]);
                        break;
                    }
            gains[2 * i] = hypot(mc, ms) * f;
            gains[2 * i + 1] = hypot(uc, us) / spread * half * f;
        }
    } else {
        PyErr_SetString(PyExc_ValueError, "fiducial kernel: inconsistent locking sizes");
    }
    release(&s);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"fits", fits, METH_VARARGS,
     "Reprojection residuals and Jacobians of a stack of poses, into the given arrays."},
    {"gauss_newton", gauss_newton, METH_VARARGS,
     "Undamped Gauss-Newton steps of a stack of poses, in place, and their last fits."},
    {"moved", moved, METH_VARARGS,
     "A stack of poses stepped by [position, rotation] deltas, into the given arrays."},
    {"crossings", crossings, METH_VARARGS,
     "Each profile's rising crossing of its level nearest the centre, or inf."},
    {"lines", lines, METH_VARARGS,
     "Each side's weighted line fit: mean, deviations, principal axis, into the given arrays."},
    {"code_crossings", code_crossings, METH_VARARGS,
     "The modelled profiles' crossings across thin sides (border.crossing_bias), into out."},
    {"corner_covariance", corner_covariance, METH_VARARGS,
     "Each marker's corners' joint covariance from its four line fits, into the given array."},
    {"locking_terms", locking_terms, METH_VARARGS,
     "Each side's pixel-locking share of its scatter and its line gains, into the given arrays."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void) { return uma_twin_module(&module); }
