/* The compiled twin of the dead reckoner's step (services/accel_rig/integrator.py): the
 * RK4 step of DeadReckoner._step with its error propagation, and the arrays of
 * DeadReckoner.estimate.  The same operations in the same order as the Python floats
 * (interpolation, eq. 4.42 solves, quaternion RK4, rotations), so the state is the same to
 * the bit where the compiler keeps IEEE order (setup.py turns floating-point contraction
 * off); the matrix products are plain loops in place of numpy's, equal to float rounding.
 * Optional: when this does not build, the integrator runs in pure Python.
 *
 * The constants of a dead reckoner come as one float64 array (integrator._native_constants):
 *   [n, rate_hz, omega_max^2, max_variance, g (3), corr (6 x 6), gk (6 x n), noise_var_k (n),
 *    cal blocks (n x 4 x 4)?]
 * the cal blocks present only with a calibration covariance. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <string.h>

#define MAX_N 32 /* accelerometers; a rig has 6 or 9 */
#define E 12     /* error state [phi, rho, dv, domega] */

typedef struct {
    Py_ssize_t n;
    double rate, omega_max_sq, max_variance, g[3];
    const double *corr, *gk, *noise, *cal; /* cal NULL without a calibration covariance */
} consts_t;

typedef struct { Py_buffer view; int held; } buf_t;

/* A C-contiguous float64 buffer of exactly n doubles (writable if asked). */
static int get_doubles(PyObject *obj, Py_ssize_t n, int writable, buf_t *b, const char *what) {
    int flags = PyBUF_FORMAT | PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    b->held = 0;
    if (PyObject_GetBuffer(obj, &b->view, flags) < 0) return 0;
    b->held = 1;
    const char *f = b->view.format;
    if (b->view.itemsize == 8 && (n < 0 || b->view.len == n * 8) && f != NULL
        && (strcmp(f, "d") == 0 || strcmp(f, "<d") == 0))
        return 1;
    if (n < 0)
        PyErr_Format(PyExc_ValueError, "%s: expected a contiguous float64 array", what);
    else
        PyErr_Format(PyExc_ValueError, "%s: expected a contiguous float64 array of %zd", what, n);
    return 0;
}

static void release(buf_t *b) {
    if (b->held) PyBuffer_Release(&b->view);
    b->held = 0;
}

static int parse_consts(buf_t *b, consts_t *c) {
    const double *d = (const double *)b->view.buf;
    Py_ssize_t len = b->view.len / 8;
    if (len < 1 || !(d[0] >= 1 && d[0] <= MAX_N)) goto bad;
    c->n = (Py_ssize_t)d[0];
    Py_ssize_t base = 7 + 36 + 7 * c->n;
    if (len != base && len != base + 16 * c->n) goto bad;
    c->rate = d[1];
    c->omega_max_sq = d[2];
    c->max_variance = d[3];
    memcpy(c->g, d + 4, sizeof c->g);
    c->corr = d + 7;
    c->gk = c->corr + 36;
    c->noise = c->gk + 6 * c->n;
    c->cal = len == base ? NULL : c->noise + c->n;
    return 1;
bad:
    PyErr_SetString(PyExc_ValueError, "dead reckoner constants: malformed array");
    return 0;
}

/* n floats of a list or tuple into out. */
static int read_floats(PyObject *seq, double *out, Py_ssize_t n) {
    if (!(PyList_Check(seq) || PyTuple_Check(seq)) || PySequence_Fast_GET_SIZE(seq) != n) {
        PyErr_Format(PyExc_ValueError, "expected a list of %zd floats", n);
        return 0;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t i = 0; i < n; i++) {
        out[i] = PyFloat_AsDouble(items[i]);
        if (out[i] == -1.0 && PyErr_Occurred()) return 0;
    }
    return 1;
}

static PyObject *float_list(const double *v, Py_ssize_t n) {
    PyObject *l = PyList_New(n);
    if (l == NULL) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *x = PyFloat_FromDouble(v[i]);
        if (x == NULL) { Py_DECREF(l); return NULL; }
        PyList_SET_ITEM(l, i, x);
    }
    return l;
}

/* ------------------------------------------------------------------ small vectors */

/* _interpolate: Lagrange over m (1-3) samples at tau. */
static void interpolate(int m, const double *ts, double xs[][6], double tau, double *out) {
    if (m == 1) {
        memcpy(out, xs[0], 6 * sizeof(double));
        return;
    }
    if (m == 2) {
        double ta = ts[0], tb = ts[1];
        double wa = (tau - tb) / (ta - tb), wb = (tau - ta) / (tb - ta);
        for (int i = 0; i < 6; i++) out[i] = wa * xs[0][i] + wb * xs[1][i];
        return;
    }
    double ta = ts[0], tb = ts[1], tc = ts[2];
    if (tau == tb || tau == tc) {
        memcpy(out, tau == tb ? xs[1] : xs[2], 6 * sizeof(double));
        return;
    }
    double dab = ta - tb, dac = ta - tc, dbc = tb - tc;
    double ua = tau - ta, ub = tau - tb, uc = tau - tc;
    double wa = ub * uc / (dab * dac), wb = -ua * uc / (dab * dbc), wc = ua * ub / (dac * dbc);
    for (int i = 0; i < 6; i++) out[i] = wa * xs[0][i] + wb * xs[1][i] + wc * xs[2][i];
}

/* RigLayout.solve_floats: projected readings plus the centripetal correction at w. */
static void solve(const double *corr, const double *p, const double *w, double *out) {
    double x = w[0], y = w[1], z = w[2];
    double xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    for (int r = 0; r < 6; r++) {
        const double *c = corr + 6 * r;
        out[r] = p[r] + c[0] * xx + c[1] * yy + c[2] * zz + c[3] * xy + c[4] * yz + c[5] * xz;
    }
}

/* RigLayout.omega_jacobian_floats: 6 rows of 3. */
static void omega_jacobian(const double *corr, const double *w, double J[6][3]) {
    double x = w[0], y = w[1], z = w[2];
    double x2 = 2.0 * x, y2 = 2.0 * y, z2 = 2.0 * z;
    for (int r = 0; r < 6; r++) {
        const double *c = corr + 6 * r;
        J[r][0] = c[0] * x2 + c[3] * y + c[5] * z;
        J[r][1] = c[1] * y2 + c[3] * x + c[4] * z;
        J[r][2] = c[2] * z2 + c[4] * y + c[5] * x;
    }
}

/* _quaternion_rk4: the end quaternion (not normalised) and those of stages 2-4. */
static void quaternion_rk4(const double *q0, double ws[4][3], double h, double *end,
                           double stages[3][4]) {
    double x0 = q0[0], y0 = q0[1], z0 = q0[2], s0 = q0[3];
    double x = x0, y = y0, z = z0, s = s0, k[4][4];
    for (int i = 0; i < 4; i++) {
        double a = ws[i][0], b = ws[i][1], c = ws[i][2];
        k[i][0] = 0.5 * (s * a + y * c - z * b);
        k[i][1] = 0.5 * (s * b + z * a - x * c);
        k[i][2] = 0.5 * (s * c + x * b - y * a);
        k[i][3] = -0.5 * (x * a + y * b + z * c);
        if (i < 3) {
            double d = i == 2 ? h : 0.5 * h;
            x = x0 + d * k[i][0]; y = y0 + d * k[i][1]; z = z0 + d * k[i][2];
            s = s0 + d * k[i][3];
            stages[i][0] = x; stages[i][1] = y; stages[i][2] = z; stages[i][3] = s;
        }
    }
    double h6 = h / 6.0;
    for (int j = 0; j < 4; j++)
        end[j] = q0[j] + h6 * (k[0][j] + 2.0 * k[1][j] + 2.0 * k[2][j] + k[3][j]);
}

/* _rotation: R(q / |q|), row-major. */
static void rotation(const double *q, double *R) {
    double x = q[0], y = q[1], z = q[2], s = q[3];
    double xx = x * x, yy = y * y, zz = z * z, ss = s * s;
    double n = 1.0 / (xx + yy + zz + ss);
    double xy = 2 * x * y, xz = 2 * x * z, yz = 2 * y * z, xs = 2 * x * s, ys = 2 * y * s,
           zs = 2 * z * s;
    R[0] = n * (ss + xx - yy - zz); R[1] = n * (xy - zs); R[2] = n * (xz + ys);
    R[3] = n * (xy + zs); R[4] = n * (ss - xx + yy - zz); R[5] = n * (yz - xs);
    R[6] = n * (xz - ys); R[7] = n * (yz + xs); R[8] = n * (ss - xx - yy + zz);
}

/* _rotate: R(q / |q|) v without forming R. */
static void rotate(const double *q, const double *v, double *out) {
    double x = q[0], y = q[1], z = q[2], s = q[3];
    double a = v[0], b = v[1], c = v[2];
    double uu = x * x + y * y + z * z;
    double n = 1.0 / (uu + s * s);
    double k = s * s - uu;
    double d = 2.0 * (x * a + y * b + z * c);
    double s2 = 2.0 * s;
    out[0] = n * (k * a + d * x + s2 * (y * c - z * b));
    out[1] = n * (k * b + d * y + s2 * (z * a - x * c));
    out[2] = n * (k * c + d * z + s2 * (x * b - y * a));
}

static void mat_vec(const double *R, const double *v, double *out) {
    double a = v[0], b = v[1], c = v[2];
    out[0] = R[0] * a + R[1] * b + R[2] * c;
    out[1] = R[3] * a + R[4] * b + R[5] * c;
    out[2] = R[6] * a + R[7] * b + R[8] * c;
}

/* ------------------------------------------------------------------ covariance */

/* The error dynamics A (12 x 12) and Bk (12 x n) of _propagate / _error_dynamics_layout. */
static void dynamics(const consts_t *c, const double *R, const double *f, const double *w,
                     const double *p, const double *v, double A[E][E], double Bk[E][MAX_N]) {
    double J[6][3], u[3];
    Py_ssize_t n = c->n;
    omega_jacobian(c->corr, w, J);
    mat_vec(R, f, u);
    memset(A, 0, sizeof(double) * E * E);
    memset(Bk, 0, sizeof(double) * E * MAX_N);
    for (int i = 0; i < 3; i++) {
        const double *r = R + 3 * i;
        A[3 + i][6 + i] = 1.0;
        for (int j = 0; j < 3; j++) {
            A[i][9 + j] = r[j];
            A[6 + i][9 + j] = r[0] * J[0][j] + r[1] * J[1][j] + r[2] * J[2][j];
            A[9 + i][9 + j] = J[3 + i][j];
        }
        for (Py_ssize_t j = 0; j < n; j++) {
            Bk[6 + i][j] = c->gk[j] * r[0] + c->gk[n + j] * r[1] + c->gk[2 * n + j] * r[2];
            Bk[9 + i][j] = c->gk[(3 + i) * n + j];
        }
    }
    /* [v]x and -[R f]x (off-diagonal), [p]x R */
    A[3][1] = -v[2]; A[3][2] = v[1]; A[4][0] = v[2]; A[4][2] = -v[0];
    A[5][0] = -v[1]; A[5][1] = v[0];
    A[6][1] = u[2]; A[6][2] = -u[1]; A[7][0] = -u[2]; A[7][2] = u[0];
    A[8][0] = u[1]; A[8][1] = -u[0];
    for (int j = 0; j < 3; j++) {
        A[3][9 + j] = p[1] * R[6 + j] - p[2] * R[3 + j];
        A[4][9 + j] = p[2] * R[j] - p[0] * R[6 + j];
        A[5][9 + j] = p[0] * R[3 + j] - p[1] * R[j];
    }
}

/* out = a b (a: r x k, b: k x m, row strides given), summed over k in order.  The left
 * operands (Ah, F, the noise's Bk) are mostly exact zeros, their block structure, whose
 * terms are skipped: they add nothing while the right operand is finite.  P and S enter
 * finite (a state with a non-finite variance is refused as diverged, and S, the same error's
 * share from constant reading errors, grows with P); where the step itself overflows, its
 * inf or NaN reaches P's diagonal through the terms kept, and the step diverges either way
 * (tests/test_accel_native.py: the same message as numpy's products). */
static void mat_mul(const double *a, int sa, const double *b, int sb, int r, int k, int m,
                    double *out, int so) {
    for (int i = 0; i < r; i++) {
        double *o = out + i * so;
        for (int j = 0; j < m; j++) o[j] = 0.0;
        for (int l = 0; l < k; l++) {
            double x = a[i * sa + l];
            if (x == 0.0) continue;
            const double *bl = b + l * sb;
            for (int j = 0; j < m; j++) o[j] += x * bl[j];
        }
    }
}

/* out = Sr cal Sr^T (r x r, r <= 6) for r rows Sr of a sensitivity (4n wide): cal is
 * block-diagonal, 4x4 per accelerometer, so only its blocks are multiplied. */
static void cal_quadratic(const consts_t *c, const double *Sr, int r, double *out) {
    Py_ssize_t m = 4 * c->n;
    double T[6][4 * MAX_N];
    for (Py_ssize_t j = 0; j < c->n; j++)
        mat_mul(Sr + 4 * j, (int)m, c->cal + 16 * j, 4, r, 4, 4, &T[0][4 * j], 4 * MAX_N);
    for (int a = 0; a < r; a++)
        for (int b = 0; b < r; b++) {
            double s = 0.0;
            for (Py_ssize_t l = 0; l < m; l++) s += T[a][l] * Sr[b * m + l];
            out[r * a + b] = s;
        }
}

/* _tilt_covariance: the 3x3 block of P plus S3 cal S3^T (with a calibration covariance). */
static void tilt_covariance(const consts_t *c, const double *P, const double *S, double *C) {
    double SC[9] = {0.0};
    if (c->cal != NULL) cal_quadratic(c, S, 3, SC);
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) C[3 * a + b] = SC[3 * a + b] + P[a * E + b];
}

/* _along_rms: the root mean square of the second-order term along u per unit |u|, from
 * the trace t and the sum of squares q of Cp. */
static double along_rms(double t, double q) {
    double d = sqrt(fmax(0.5 * q - 0.25 * t * t, 0.0));
    double lam[2] = {fmax(0.5 * t + d, 0.0), fmax(0.5 * t - d, 0.0)};
    double mean = 0.0, var = 0.0;
    for (int i = 0; i < 2; i++) mean += -expm1(-0.5 * lam[i]);
    for (int i = 0; i < 2; i++) {
        double e = expm1(-lam[i]);
        var += 0.5 * e * e;
    }
    return sqrt(mean * mean + var);
}

/* _second_order: along_rms(tr Cp, sum Cp^2) u, Cp = (I - u u^T / u.u) C (I - u u^T / u.u). */
static void second_order(const double *C, const double *u, double *spread) {
    double uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    if (uu == 0.0) {
        spread[0] = spread[1] = spread[2] = 0.0;
        return;
    }
    double perp[9], PC[9], M[9], ss = 0.0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) perp[3 * i + j] = (i == j ? 1.0 : 0.0) - u[i] * u[j] / uu;
    mat_mul(perp, 3, C, 3, 3, 3, 3, PC, 3);
    mat_mul(PC, 3, perp, 3, 3, 3, 3, M, 3);
    for (int i = 0; i < 9; i++) ss += M[i] * M[i];
    double k = along_rms(M[0] + M[4] + M[8], ss);
    for (int i = 0; i < 3; i++) spread[i] = k * u[i];
}

/* _propagate: P_out = F P F^T + noise, S_out = F S + outer(Bk, [h, h f]) (cal only),
 * D_out = F D + h spread (rows 6:9). */
static void propagate(const consts_t *c, const double *P, const double *S, const double *D,
                      double h, const double *R, const double *f, const double *w,
                      const double *p, const double *v, const double *spread, double *P_out,
                      double *S_out, double *D_out) {
    double A[E][E], Bk[E][MAX_N], Ah[E][E], A2[E][E], F[E][E], Pt[E][E], FP[E][E], PF[E][E];
    double Bw[E][MAX_N], BkT[MAX_N][E];
    Py_ssize_t n = c->n, m = 4 * n;
    dynamics(c, R, f, w, p, v, A, Bk);
    for (int i = 0; i < E; i++)
        for (int j = 0; j < E; j++) Ah[i][j] = A[i][j] * h;
    mat_mul(&Ah[0][0], E, &Ah[0][0], E, E, E, E, &A2[0][0], E);
    for (int i = 0; i < E; i++)
        for (int j = 0; j < E; j++) {
            F[i][j] = ((i == j ? 1.0 : 0.0) + Ah[i][j]) + 0.5 * A2[i][j];
            Pt[j][i] = P[i * E + j];
        }
    /* F P F^T as F (F P^T)^T: F on the left of both products (its zeros skipped) */
    mat_mul(&F[0][0], E, &Pt[0][0], E, E, E, E, &FP[0][0], E);
    for (int i = 0; i < E; i++)
        for (int j = 0; j < E; j++) PF[j][i] = FP[i][j];
    mat_mul(&F[0][0], E, &PF[0][0], E, E, E, E, P_out, E);
    double scale = h / c->rate;
    for (int i = 0; i < E; i++)
        for (Py_ssize_t j = 0; j < n; j++) {
            Bw[i][j] = Bk[i][j] * (c->noise[j] * scale);
            BkT[j][i] = Bk[i][j];
        }
    double noise[E][E];
    mat_mul(&Bw[0][0], MAX_N, &BkT[0][0], E, E, (int)n, E, &noise[0][0], E);
    for (int i = 0; i < E * E; i++) P_out[i] += (&noise[0][0])[i];
    mat_mul(&F[0][0], E, D, 1, E, E, 1, D_out, 1);
    for (int i = 0; i < 3; i++) D_out[6 + i] += h * spread[i];
    if (c->cal == NULL) return;
    mat_mul(&F[0][0], E, S, (int)m, E, E, (int)m, S_out, (int)m);
    double k[4] = {h, h * f[0], h * f[1], h * f[2]};
    for (int i = 0; i < E; i++)
        for (Py_ssize_t j = 0; j < n; j++)
            for (int l = 0; l < 4; l++) S_out[i * m + 4 * j + l] += Bk[i][j] * k[l];
}

/* ------------------------------------------------------------------ the step */

/* Readings of the step's samples: a list of 1-3 (motion time, 6 projected floats). */
static int read_samples(PyObject *samples, double *ts, double xs[][6]) {
    if (!PyList_Check(samples) || PyList_GET_SIZE(samples) < 1 || PyList_GET_SIZE(samples) > 3) {
        PyErr_SetString(PyExc_ValueError, "step: expected a list of 1 to 3 samples");
        return -1;
    }
    int m = (int)PyList_GET_SIZE(samples);
    for (int i = 0; i < m; i++) {
        PyObject *s = PyList_GET_ITEM(samples, i);
        if (!PyTuple_Check(s) || PyTuple_GET_SIZE(s) != 2) {
            PyErr_SetString(PyExc_ValueError, "step: a sample is a (time, readings) tuple");
            return -1;
        }
        ts[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(s, 0));
        if (ts[i] == -1.0 && PyErr_Occurred()) return -1;
        if (!read_floats(PyTuple_GET_ITEM(s, 1), xs[i], 6)) return -1;
    }
    return m;
}

typedef struct { double t, p[3], q[4], v[3], w[3]; } vec_state_t;

/* The state's t, p, q, v, w (a _State: a tuple whose items 5, 6 and 7 are P, S and D). */
static int read_state(PyObject *x, vec_state_t *s) {
    if (!PyTuple_Check(x) || PyTuple_GET_SIZE(x) != 8) {
        PyErr_SetString(PyExc_ValueError, "step: expected a _State");
        return 0;
    }
    s->t = PyFloat_AsDouble(PyTuple_GET_ITEM(x, 0));
    if (s->t == -1.0 && PyErr_Occurred()) return 0;
    return read_floats(PyTuple_GET_ITEM(x, 1), s->p, 3)
        && read_floats(PyTuple_GET_ITEM(x, 2), s->q, 4)
        && read_floats(PyTuple_GET_ITEM(x, 3), s->v, 3)
        && read_floats(PyTuple_GET_ITEM(x, 4), s->w, 3);
}

/* DeadReckoner._step before its divergence check: RK4 from x to t1 over the samples. */
static void rk4_step(const consts_t *c, const vec_state_t *x, int m, const double *ts,
                     double xs[][6], double t1, const double *P, const double *S,
                     const double *D, vec_state_t *out, double *q_norm, double *P_out,
                     double *S_out, double *D_out) {
    double h = t1 - x->t, hh = 0.5 * h;
    double x0[6], xm[6], x1[6], s1[6], s2[6], s3[6], s4[6], ws[4][3], end[4], st[3][4];
    interpolate(m, ts, xs, x->t, x0);
    interpolate(m, ts, xs, x->t + hh, xm);
    interpolate(m, ts, xs, t1, x1);
    const double *w0 = x->w;
    memcpy(ws[0], w0, sizeof ws[0]);
    solve(c->corr, x0, ws[0], s1);
    for (int i = 0; i < 3; i++) ws[1][i] = w0[i] + hh * s1[3 + i];
    solve(c->corr, xm, ws[1], s2);
    for (int i = 0; i < 3; i++) ws[2][i] = w0[i] + hh * s2[3 + i];
    solve(c->corr, xm, ws[2], s3);
    for (int i = 0; i < 3; i++) ws[3][i] = w0[i] + h * s3[3 + i];
    solve(c->corr, x1, ws[3], s4);
    quaternion_rk4(x->q, ws, h, end, st);
    double R2[9], a1[3], a2[3], a3[3], a4[3], pm[3], vm[3];
    rotation(st[0], R2);
    rotate(x->q, s1, a1);
    mat_vec(R2, s2, a2);
    rotate(st[1], s3, a3);
    rotate(st[2], s4, a4);
    double Ct[9], spread[3];
    tilt_covariance(c, P, S, Ct);
    second_order(Ct, a2, spread);
    double h6 = h / 6.0, hh6 = h * h / 6.0;
    for (int i = 0; i < 3; i++) {
        double gi = c->g[i];
        out->p[i] = x->p[i] + h * x->v[i]
                    + hh6 * ((a1[i] + gi) + (a2[i] + gi) + (a3[i] + gi));
        out->v[i] = x->v[i] + h6 * ((a1[i] + gi) + 2.0 * (a2[i] + gi) + 2.0 * (a3[i] + gi)
                                    + (a4[i] + gi));
        out->w[i] = w0[i] + h6 * (s1[3 + i] + 2.0 * s2[3 + i] + 2.0 * s3[3 + i] + s4[3 + i]);
        pm[i] = 0.5 * (out->p[i] + x->p[i]);
        vm[i] = 0.5 * (out->v[i] + x->v[i]);
    }
    propagate(c, P, S, D, h, R2, s2, ws[1], pm, vm, spread, P_out, S_out, D_out);
    double a = end[0], b = end[1], cc = end[2], d = end[3];
    double norm = sqrt(a * a + b * b + cc * cc + d * d);
    for (int i = 0; i < 4; i++) out->q[i] = end[i] / norm;
    out->t = t1;
    *q_norm = norm;
}

/* step(consts, x, samples, t1, P_out, S_out, D_out)
 *   -> (p, q, v, w, q_norm, var_sum, var_max, fine):
 * the new state's vectors as lists of floats, the norm of its quaternion before
 * normalisation, the sum and largest of P_out's diagonal, and whether _divergence would
 * find nothing (the same tests, so that Python only words a divergence); P_out (12 x 12)
 * and, with a calibration covariance, S_out (12 x 4n) are filled, and D_out (12). */
static PyObject *step(PyObject *Py_UNUSED(self), PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "step: expected 7 arguments");
        return NULL;
    }
    buf_t cb = {0}, pb = {0}, sb = {0}, db = {0}, po = {0}, so = {0}, dout = {0};
    PyObject *result = NULL;
    consts_t c;
    vec_state_t x, out;
    double ts[3], xs[3][6], q_norm;
    int m;
    double t1 = PyFloat_AsDouble(args[3]);
    if ((t1 == -1.0 && PyErr_Occurred()) || !get_doubles(args[0], -1, 0, &cb, "constants")
        || !parse_consts(&cb, &c) || !read_state(args[1], &x)
        || (m = read_samples(args[2], ts, xs)) < 0
        || !get_doubles(PyTuple_GET_ITEM(args[1], 5), E * E, 0, &pb, "P")
        || !get_doubles(PyTuple_GET_ITEM(args[1], 6), E * 4 * c.n, 0, &sb, "S")
        || !get_doubles(PyTuple_GET_ITEM(args[1], 7), E, 0, &db, "D")
        || !get_doubles(args[4], E * E, 1, &po, "P_out")
        || (c.cal != NULL && !get_doubles(args[5], E * 4 * c.n, 1, &so, "S_out"))
        || !get_doubles(args[6], E, 1, &dout, "D_out"))
        goto done;
    rk4_step(&c, &x, m, ts, xs, t1, pb.view.buf, sb.view.buf, db.view.buf, &out, &q_norm,
             po.view.buf, c.cal != NULL ? so.view.buf : NULL, dout.view.buf);
    const double *P_new = po.view.buf;
    double var_sum = 0.0, var_max = P_new[0];
    for (int i = 0; i < E; i++) {
        double d = P_new[i * (E + 1)];
        var_sum += d;
        if (d > var_max) var_max = d;
    }
    double ww = out.w[0] * out.w[0] + out.w[1] * out.w[1] + out.w[2] * out.w[2];
    int fine = isfinite(var_sum + ww + q_norm) && q_norm >= 1e-6 && ww <= c.omega_max_sq
               && var_max <= c.max_variance;
    result = Py_BuildValue("(NNNNdddO)", float_list(out.p, 3), float_list(out.q, 4),
                           float_list(out.v, 3), float_list(out.w, 3), q_norm, var_sum,
                           var_max, fine ? Py_True : Py_False);
done:
    release(&cb); release(&pb); release(&sb); release(&db); release(&po); release(&so);
    release(&dout);
    return result;
}

/* estimate(consts, x, vec_out, C_out, S6_out): DeadReckoner.estimate's arrays of the state
 * x: its p, q, v, w (vec_out, 13), the 6x6 pose covariance, symmetrised, in geometry's
 * order [rho, phi] (C_out), and with a calibration covariance the pose rows of S (S6_out)
 * and S6 cal S6^T added to C (cal is block-diagonal: 4x4 per accelerometer, so only its
 * blocks are multiplied); then the pose rows of D, d d^T, added. */
static PyObject *estimate(PyObject *Py_UNUSED(self), PyObject *const *args, Py_ssize_t nargs) {
    static const int order[6] = {3, 4, 5, 0, 1, 2};
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "estimate: expected 5 arguments");
        return NULL;
    }
    buf_t cb = {0}, pb = {0}, sb = {0}, db = {0}, vo = {0}, co = {0}, so = {0};
    consts_t c;
    vec_state_t x;
    PyObject *result = NULL;
    if (!get_doubles(args[0], -1, 0, &cb, "constants") || !parse_consts(&cb, &c)
        || !read_state(args[1], &x)
        || !get_doubles(PyTuple_GET_ITEM(args[1], 5), E * E, 0, &pb, "P")
        || !get_doubles(PyTuple_GET_ITEM(args[1], 6), E * 4 * c.n, 0, &sb, "S")
        || !get_doubles(PyTuple_GET_ITEM(args[1], 7), E, 0, &db, "D")
        || !get_doubles(args[2], 13, 1, &vo, "vec_out")
        || !get_doubles(args[3], 36, 1, &co, "C_out")
        || (c.cal != NULL && !get_doubles(args[4], 24 * c.n, 1, &so, "S6_out")))
        goto done;
    double *vec = vo.view.buf;
    memcpy(vec, x.p, sizeof x.p);
    memcpy(vec + 3, x.q, sizeof x.q);
    memcpy(vec + 7, x.v, sizeof x.v);
    memcpy(vec + 10, x.w, sizeof x.w);
    const double *P = pb.view.buf, *S = sb.view.buf;
    double *C = co.view.buf, M[6][6];
    Py_ssize_t m = 4 * c.n;
    for (int a = 0; a < 6; a++)
        for (int b = 0; b < 6; b++) M[a][b] = P[order[a] * E + order[b]];
    if (c.cal != NULL) {
        double *S6 = so.view.buf, SC[6][6];
        for (int a = 0; a < 6; a++) memcpy(S6 + a * m, S + order[a] * m, m * sizeof(double));
        cal_quadratic(&c, S6, 6, &SC[0][0]);
        for (int a = 0; a < 6; a++)
            for (int b = 0; b < 6; b++) M[a][b] = SC[a][b] + M[a][b];
    }
    const double *D = db.view.buf;
    for (int a = 0; a < 6; a++)
        for (int b = 0; b < 6; b++) M[a][b] = M[a][b] + D[order[a]] * D[order[b]];
    for (int a = 0; a < 6; a++)
        for (int b = 0; b < 6; b++) C[6 * a + b] = (M[a][b] + M[b][a]) * 0.5;
    result = Py_NewRef(Py_None);
done:
    release(&cb); release(&pb); release(&sb); release(&db); release(&vo); release(&co);
    release(&so);
    return result;
}

static PyMethodDef methods[] = {
    {"step", (PyCFunction)(void (*)(void))step, METH_FASTCALL,
     "One RK4 step of the dead reckoner with its error propagation."},
    {"estimate", (PyCFunction)(void (*)(void))estimate, METH_FASTCALL,
     "The estimate's vectors, 6x6 pose covariance and calibration sensitivity."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_step", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__step(void) { return uma_twin_module(&module); }
