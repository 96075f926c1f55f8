/* The compiled twin of services/outside_in/pose.py's _gauss_newton: a body's pose fitted
 * to its stacked marker images by Gauss-Newton steps (each a left perturbation of the
 * pose, relinearised where it lands), with the Jacobian at the solution; and of
 * motion.py's filter step (below), which costs the same interpreter overhead.
 *
 * The same algorithm, steps and tests as the Python one: residuals in units of each
 * image's std, the 6 x 6 normal equations solved by LU with partial pivoting (LAPACK's
 * gesv, which numpy's solve calls, does the same), a step taken only when it does not
 * raise the cost, converged when no component of the step is above the tolerance.  The
 * sums run in another order than numpy's matrix products (and einsum's), so results
 * agree to rounding (about 1e-15 relative), not to the bit.  The interpreter was the
 * cost: about 70 us per step in 25 small numpy calls, three bodies a frame set at 120 Hz.
 * Optional: when this does not build, pose.py runs in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* agent.geometry's small angle, below which sin(x/2)/x takes its series */
#define SMALL_ANGLE 1e-8

typedef struct {
    Py_ssize_t k;
    const double *Rcw, *tcw, *xy, *scale, *turn, *shift, *body;
} stack_t;

/* geometry.rodrigues: rotation vector -> quaternion (exponential map) -> matrix */
static void rodrigues(const double r[3], double R[9]) {
    double th = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
    double k1 = th < SMALL_ANGLE ? 0.5 - th * th / 48.0 : sin(0.5 * th) / th;
    double x = r[0] * k1, y = r[1] * k1, z = r[2] * k1, w = cos(0.5 * th);
    R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - z * w);     R[2] = 2 * (x * z + y * w);
    R[3] = 2 * (x * y + z * w);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - x * w);
    R[6] = 2 * (x * z - y * w);     R[7] = 2 * (y * z + x * w);     R[8] = 1 - 2 * (x * x + y * y);
}

static void matmul3(const double A[9], const double B[9], double C[9]) {
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}

/* Marker image n's camera point and arm at pose (p, R): arm = turn R m,
 * xc = R_cw (arm + p + shift) + t_cw. */
static void camera_point(const stack_t *s, Py_ssize_t n, const double p[3], const double R[9],
                         double xc[3], double arm[3]) {
    const double *m = s->body + 3 * n, *T = s->turn + 9 * n, *sh = s->shift + 3 * n;
    const double *C = s->Rcw + 9 * n, *t = s->tcw + 3 * n;
    double b[3], w[3];
    for (int i = 0; i < 3; i++) b[i] = R[3 * i] * m[0] + R[3 * i + 1] * m[1] + R[3 * i + 2] * m[2];
    for (int i = 0; i < 3; i++) {
        arm[i] = T[3 * i] * b[0] + T[3 * i + 1] * b[1] + T[3 * i + 2] * b[2];
        w[i] = arm[i] + p[i] + sh[i];
    }
    for (int i = 0; i < 3; i++) xc[i] = C[3 * i] * w[0] + C[3 * i + 1] * w[1] + C[3 * i + 2] * w[2] + t[i];
}

/* Residuals (2k) at (p, R); their sum of squares. */
static double residual(const stack_t *s, const double p[3], const double R[9], double *r) {
    double cost = 0.0;
    for (Py_ssize_t n = 0; n < s->k; n++) {
        double xc[3], arm[3];
        camera_point(s, n, p, R, xc, arm);
        for (int i = 0; i < 2; i++) {
            double v = (xc[i] / xc[2] - s->xy[2 * n + i]) * s->scale[n];
            r[2 * n + i] = v;
            cost += v * v;
        }
    }
    return cost;
}

/* pose.py's _Stack.jacobian at (p, R): (2k x 6) by [dp, phi], row-major. */
static void jacobian(const stack_t *s, const double p[3], const double R[9], double *J) {
    for (Py_ssize_t n = 0; n < s->k; n++) {
        double xc[3], a[3];
        camera_point(s, n, p, R, xc, a);
        const double *C = s->Rcw + 9 * n;
        double z = xc[2], sc = s->scale[n];
        for (int i = 0; i < 2; i++) {
            double proj = xc[i] / z, d[3];
            for (int j = 0; j < 3; j++) d[j] = (C[3 * i + j] - proj * C[6 + j]) / z;
            double *row = J + (2 * n + i) * 6;
            /* d world / d phi = -[arm]x */
            row[0] = d[0] * sc; row[1] = d[1] * sc; row[2] = d[2] * sc;
            row[3] = (d[1] * (-a[2]) + d[2] * a[1]) * sc;
            row[4] = (d[0] * a[2] + d[2] * (-a[0])) * sc;
            row[5] = (d[0] * (-a[1]) + d[1] * a[0]) * sc;
        }
    }
}

/* A X = B for 6 x 6 A and 6 x m B (row-major) by LU with partial pivoting (A and B
 * overwritten, X in B); 0 when singular. */
static int solve6m(double A[36], double *B, int m) {
    for (int c = 0; c < 6; c++) {
        int piv = c;
        for (int i = c + 1; i < 6; i++)
            if (fabs(A[6 * i + c]) > fabs(A[6 * piv + c])) piv = i;
        if (A[6 * piv + c] == 0.0) return 0;
        if (piv != c) {
            for (int j = 0; j < 6; j++) {
                double t = A[6 * c + j]; A[6 * c + j] = A[6 * piv + j]; A[6 * piv + j] = t;
            }
            for (int j = 0; j < m; j++) {
                double t = B[m * c + j]; B[m * c + j] = B[m * piv + j]; B[m * piv + j] = t;
            }
        }
        for (int i = c + 1; i < 6; i++) {
            double f = A[6 * i + c] / A[6 * c + c];
            for (int j = c; j < 6; j++) A[6 * i + j] -= f * A[6 * c + j];
            for (int j = 0; j < m; j++) B[m * i + j] -= f * B[m * c + j];
        }
    }
    for (int i = 5; i >= 0; i--)
        for (int j = 0; j < m; j++) {
            double v = B[m * i + j];
            for (int l = i + 1; l < 6; l++) v -= A[6 * i + l] * B[m * l + j];
            B[m * i + j] = v / A[6 * i + i];
        }
    return 1;
}

/* 1: converged (p, R, J at the solution); 0: a step raised the cost, the equations were
 * singular or it did not converge in ``steps``. */
static int fit(const stack_t *s, double p[3], double R[9], int steps, double tol, double *r,
               double *J) {
    double cost = residual(s, p, R, r);
    for (int it = 0; it < steps; it++) {
        jacobian(s, p, R, J);
        double A[36] = {0}, g[6] = {0};
        for (Py_ssize_t q = 0; q < 2 * s->k; q++) {
            const double *row = J + 6 * q;
            for (int i = 0; i < 6; i++) {
                g[i] -= row[i] * r[q];
                for (int j = 0; j < 6; j++) A[6 * i + j] += row[i] * row[j];
            }
        }
        if (!solve6m(A, g, 1)) return 0;
        double p_new[3], R_new[9], dR[9];
        for (int i = 0; i < 3; i++) p_new[i] = p[i] + g[i];
        rodrigues(g + 3, dR);
        matmul3(dR, R, R_new);
        double new_cost = residual(s, p_new, R_new, r);
        if (!(new_cost <= cost * (1 + 1e-9))) return 0;
        memcpy(p, p_new, sizeof p_new);
        memcpy(R, R_new, sizeof R_new);
        cost = new_cost;
        double big = 0.0;
        for (int i = 0; i < 6; i++) big = fabs(g[i]) > big ? fabs(g[i]) : big;
        if (big < tol) {
            jacobian(s, p, R, J);
            return 1;
        }
    }
    return 0;
}

typedef struct { Py_buffer view; int held; } buf_t;

static int get(PyObject *o, Py_ssize_t n, buf_t *b, const char *what) {
    b->held = 0;
    if (PyObject_GetBuffer(o, &b->view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return 0;
    b->held = 1;
    const char *f = b->view.format;
    if (b->view.itemsize == 8 && (n < 0 ? b->view.len > 0 : b->view.len == n * 8) && f
        && (!strcmp(f, "d") || !strcmp(f, "<d")))
        return 1;
    PyErr_Format(PyExc_ValueError, "%s: expected a contiguous float64 array of %zd", what, n);
    return 0;
}

/* gauss_newton(R_cw, t_cw, xy, scale, turn, shift, body, p, R, steps, tol)
 *   -> (p, R, J) as bytes of float64 (3, 9, 2k x 6), or None (pose.py's _gauss_newton). */
static PyObject *gauss_newton(PyObject *self, PyObject *args) {
    PyObject *o[9];
    int steps;
    double tol;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOid", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &steps, &tol))
        return NULL;
    buf_t b[9];
    memset(b, 0, sizeof b);
    PyObject *res = NULL;
    double *r = NULL, *J = NULL;
    if (!get(o[3], -1, &b[3], "scale")) goto done;
    Py_ssize_t k = b[3].view.len / 8;
    static const char *what[] = {"R_cw", "t_cw", "xy", "scale", "turn", "shift", "body", "p", "R"};
    const Py_ssize_t per[] = {9, 3, 2, 1, 9, 3, 3};
    for (int i = 0; i < 9; i++) {
        if (i == 3) continue;
        Py_ssize_t n = i < 7 ? per[i] * k : (i == 7 ? 3 : 9);
        if (!get(o[i], n, &b[i], what[i])) goto done;
    }
    stack_t s = {k, b[0].view.buf, b[1].view.buf, b[2].view.buf, b[3].view.buf,
                 b[4].view.buf, b[5].view.buf, b[6].view.buf};
    double p[3], R[9];
    memcpy(p, b[7].view.buf, sizeof p);
    memcpy(R, b[8].view.buf, sizeof R);
    r = malloc(sizeof(double) * 2 * k);
    J = malloc(sizeof(double) * 12 * k);
    if (!r || !J) { PyErr_NoMemory(); goto done; }
    if (!fit(&s, p, R, steps, tol, r, J)) {
        res = Py_NewRef(Py_None);
        goto done;
    }
    res = Py_BuildValue("(y#y#y#)", (const char *)p, (Py_ssize_t)sizeof p, (const char *)R,
                        (Py_ssize_t)sizeof R, (const char *)J, (Py_ssize_t)(sizeof(double) * 12 * k));
done:
    for (int i = 0; i < 9; i++)
        if (b[i].held) PyBuffer_Release(&b[i].view);
    free(r);
    free(J);
    return res;
}

/* ------------------------------------------------------------------ the filter's step
 * motion.py's MotionFilter.innovation once it has its prediction (the covariance moved
 * over dt, F P F^T + Q, then the pose measurement's innovation, its covariance and
 * chi-square) and MotionFilter.correct (the gain, the state's correction and the Joseph
 * form).  The same arithmetic as the numpy there, summed in another order (results agree
 * to rounding). */

#define NS 15   /* error state: dp, dtheta, dv, domega, da */

/* geometry.matrix_to_quat then quat_to_rotvec: rotation matrix -> rotation vector */
static void rodrigues_inverse(const double M[9], double r[3]) {
    double m00 = M[0], m01 = M[1], m02 = M[2], m10 = M[3], m11 = M[4], m12 = M[5],
           m20 = M[6], m21 = M[7], m22 = M[8];
    double tr = m00 + m11 + m22;
    double piv[4] = {1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22};
    int best = 0;
    for (int i = 1; i < 4; i++)
        if (piv[i] > piv[best]) best = i;
    double q[4];
    if (best == 0) { q[0] = m21 - m12; q[1] = m02 - m20; q[2] = m10 - m01; q[3] = piv[0]; }
    else if (best == 1) { q[0] = piv[1]; q[1] = m01 + m10; q[2] = m02 + m20; q[3] = m21 - m12; }
    else if (best == 2) { q[0] = m01 + m10; q[1] = piv[2]; q[2] = m12 + m21; q[3] = m02 - m20; }
    else { q[0] = m02 + m20; q[1] = m12 + m21; q[2] = piv[3]; q[3] = m10 - m01; }
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    double x = q[0] / n, y = q[1] / n, z = q[2] / n, w = q[3] / n;
    if (w < 0) { x = -x; y = -y; z = -z; w = -w; }
    double sn = sqrt(x * x + y * y + z * z);
    double k = sn < SMALL_ANGLE ? 2.0 / w : 2.0 * atan2(sn, w) / sn;
    r[0] = x * k; r[1] = y * k; r[2] = z * k;
}

/* C (n x m) = A (n x l) B (l x m), or A B^T with B given as (m x l) when bt */
static void mul(const double *A, const double *B, double *C, int n, int l, int m, int bt) {
    for (int i = 0; i < n; i++)
        for (int j = 0; j < m; j++) {
            double v = 0.0;
            for (int k = 0; k < l; k++) v += A[l * i + k] * (bt ? B[l * j + k] : B[m * k + j]);
            C[m * i + j] = v;
        }
}

/* A <- 0.5 (A + A^T), n x n */
static void symmetrize(double *A, int n) {
    for (int i = 0; i < n; i++)
        for (int j = i + 1; j < n; j++) {
            double v = 0.5 * (A[n * i + j] + A[n * j + i]);
            A[n * i + j] = v; A[n * j + i] = v;
        }
}

/* the state [p, R, v, omega, a, P] as one block of doubles */
#define NX (21 + NS * NS)

static int get_state(PyObject **o, buf_t *b, double x[NX]) {
    static const char *what[] = {"p", "R", "v", "omega", "a", "P"};
    const Py_ssize_t size[] = {3, 9, 3, 3, 3, NS * NS};
    double *at = x;
    for (int i = 0; i < 6; i++) {
        if (!get(o[i], size[i], &b[i], what[i])) return 0;
        memcpy(at, b[i].view.buf, size[i] * sizeof(double));
        at += size[i];
    }
    return 1;
}

/* The prediction and a pose measurement's innovation on the state block x, whose (p, R)
 * are already the pose predicted dt ahead (0: nothing moves; W and Q are then not read):
 * x moved to the measurement's time, the innovation y, its covariance S, P H^T, the
 * chi-square and log |S|; 0 when S is singular.  mo (9, or NULL): the motion the fit
 * was given, whose difference from this state's the fit's sensitivity (H's last 9
 * columns, less) turns into the pose it expects. */
static int innovate(double x[NX], const double *W, double dt, const double *Q,
                    const double *pm, const double *Rm, const double *H, const double *noise,
                    const double *mo, double y[6], double S[36], double PHt[NS * 6],
                    double *nis, double *logdet) {
    double *p = x, *R = x + 3, *v = x + 12, *a = x + 18, *P = x + 21;
    if (dt != 0.0) {       /* the prediction: v + a dt, F P F^T + Q */
        double F[NS * NS] = {0}, FP[NS * NS];
        for (int i = 0; i < NS; i++) F[NS * i + i] = 1.0;
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) F[NS * (3 + i) + 3 + j] = W[3 * i + j];
            F[NS * i + 6 + i] = dt;                 /* p by v */
            F[NS * i + 12 + i] = 0.5 * dt * dt;     /* p by a */
            F[NS * (6 + i) + 12 + i] = dt;          /* v by a */
            F[NS * (3 + i) + 9 + i] = dt;           /* theta by omega */
            v[i] = v[i] + a[i] * dt;
        }
        mul(F, P, FP, NS, NS, NS, 0);
        mul(FP, F, P, NS, NS, NS, 1);
        for (int i = 0; i < NS * NS; i++) P[i] += Q[i];
        symmetrize(P, NS);
    }
    double RRt[9];
    for (int i = 0; i < 3; i++) y[i] = pm[i] - p[i];
    mul(Rm, R, RRt, 3, 3, 3, 1);
    rodrigues_inverse(RRt, y + 3);
    if (mo) {   /* y - sens (motion - [v, omega, a]), sens = -H[:, 6:] */
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 9; j++) y[i] += H[NS * i + 6 + j] * (mo[j] - x[12 + j]);
    }
    double S2[36], Sy[6];
    mul(P, H, PHt, NS, NS, 6, 1);
    mul(H, PHt, S, 6, NS, 6, 0);
    for (int i = 0; i < 36; i++) S[i] += noise[i];
    memcpy(S2, S, sizeof S2);
    memcpy(Sy, y, sizeof Sy);
    if (!solve6m(S2, Sy, 1)) return 0;
    *nis = 0.0;
    *logdet = 0.0;
    for (int i = 0; i < 6; i++) {
        *nis += y[i] * Sy[i];
        *logdet += log(fabs(S2[7 * i]));    /* S2 holds S's LU factor U */
    }
    return 1;
}

/* x corrected by the gain K = P H^T S^-1 and its covariance in the Joseph form
 * (I - K H) P (I - K H)^T + K noise K^T; 0 when S is singular. */
static int correct(double x[NX], const double y[6], const double *H, const double *S_in,
                   const double *PHt, const double *noise) {
    double *p = x, *R = x + 3, *v = x + 12, *om = x + 15, *a = x + 18, *P = x + 21;
    double S[36], Kt[6 * NS];    /* S^-1 PHt^T = K^T */
    memcpy(S, S_in, sizeof S);
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < NS; j++) Kt[NS * i + j] = PHt[6 * j + i];
    if (!solve6m(S, Kt, NS)) return 0;
    double K[NS * 6], dx[NS], dR[9], Rn[9];
    for (int i = 0; i < NS; i++)
        for (int j = 0; j < 6; j++) K[6 * i + j] = Kt[NS * j + i];
    mul(K, y, dx, NS, 6, 1, 0);
    for (int i = 0; i < 3; i++) {
        p[i] += dx[i]; v[i] += dx[6 + i]; om[i] += dx[9 + i]; a[i] += dx[12 + i];
    }
    rodrigues(dx + 3, dR);
    matmul3(dR, R, Rn);
    memcpy(R, Rn, sizeof Rn);
    double IKH[NS * NS], T1[NS * NS], Kn[NS * 6], KnK[NS * NS];
    mul(K, H, IKH, NS, 6, NS, 0);
    for (int i = 0; i < NS * NS; i++) IKH[i] = (i % (NS + 1) == 0 ? 1.0 : 0.0) - IKH[i];
    mul(IKH, P, T1, NS, NS, NS, 0);
    mul(T1, IKH, P, NS, NS, NS, 1);
    mul(K, noise, Kn, NS, 6, 6, 0);
    mul(Kn, K, KnK, NS, 6, NS, 1);
    for (int i = 0; i < NS * NS; i++) P[i] += KnK[i];
    symmetrize(P, NS);
    return 1;
}

/* x <- the mixture of x and x2 about x, weights w and w2 (summing to 1): x moved by the
 * mean of x2's difference from it, d = w2 (x2 - x), its covariance w (P + d d^T)
 * + w2 (P2 + (x2 - x - d)(x2 - x - d)^T). */
static void mix(double x[NX], const double x2[NX], double w, double w2) {
    double *p = x, *R = x + 3, *v = x + 12, *om = x + 15, *a = x + 18, *P = x + 21;
    double d[NS], mean[NS], spread[NS], RRt[9], dR[9], Rn[9];
    for (int i = 0; i < 3; i++) d[i] = x2[i] - p[i];
    mul(x2 + 3, R, RRt, 3, 3, 3, 1);
    rodrigues_inverse(RRt, d + 3);
    for (int i = 6; i < NS; i++) d[i] = x2[6 + i] - x[6 + i];
    for (int i = 0; i < NS; i++) {
        mean[i] = w2 * d[i];
        spread[i] = d[i] - mean[i];
    }
    for (int i = 0; i < NS; i++)
        for (int j = 0; j < NS; j++)
            P[NS * i + j] = w * (P[NS * i + j] + mean[i] * mean[j])
                            + w2 * (x2[21 + NS * i + j] + spread[i] * spread[j]);
    symmetrize(P, NS);
    for (int i = 0; i < 3; i++) {
        p[i] += mean[i]; v[i] += mean[6 + i]; om[i] += mean[9 + i]; a[i] += mean[12 + i];
    }
    rodrigues(mean + 3, dR);
    matmul3(dR, R, Rn);
    memcpy(R, Rn, sizeof Rn);
}

static void release(buf_t *b, int n) {
    for (int i = 0; i < n; i++)
        if (b[i].held) PyBuffer_Release(&b[i].view);
}

/* filter_innovation(p, R, v, omega, a, P, W, dt, Q, p_meas, R_meas, H, noise, motion)
 *   -> (x, y, S, PHt, nis) as bytes of float64 (NX, 6, 36, 90) and a float, or None when
 *   S is singular (motion.py's MotionFilter.innovation once it has its prediction: (p, R)
 *   the pose predicted at the measurement's time, dt how far that is ahead of the
 *   state; x the state there, [p, R, v, omega, a, P]). */
static PyObject *filter_innovation(PyObject *self, PyObject *args) {
    PyObject *o[14];
    double dt;
    if (!PyArg_ParseTuple(args, "OOOOOOOdOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &dt, &o[8], &o[9], &o[10], &o[11], &o[12], &o[13]))
        return NULL;
    buf_t b[14];
    memset(b, 0, sizeof b);
    PyObject *res = NULL;
    double x[NX];
    if (!get_state(o, b, x)) goto done;
    static const char *what[] = {"W", "dt", "Q", "p_meas", "R_meas", "H", "noise", "motion"};
    const Py_ssize_t size[] = {9, 0, NS * NS, 3, 9, 6 * NS, 36, 9};
    for (int i = 6; i < 14; i++) {
        if (i == 7 || (i == 13 && o[13] == Py_None)) continue;
        if (!get(o[i], size[i - 6], &b[i], what[i - 6])) goto done;
    }
    double y[6], S[36], PHt[NS * 6], nis, logdet;
    if (!innovate(x, b[6].view.buf, dt, b[8].view.buf, b[9].view.buf, b[10].view.buf,
                  b[11].view.buf, b[12].view.buf, o[13] == Py_None ? NULL : b[13].view.buf,
                  y, S, PHt, &nis, &logdet)) {
        res = Py_NewRef(Py_None);
        goto done;
    }
    res = Py_BuildValue("(y#y#y#y#d)", (const char *)x, (Py_ssize_t)sizeof x, (const char *)y,
                        (Py_ssize_t)sizeof y, (const char *)S, (Py_ssize_t)sizeof S,
                        (const char *)PHt, (Py_ssize_t)sizeof PHt, nis);
done:
    release(b, 14);
    return res;
}

/* filter_correct(p, R, v, omega, a, P, y, H, S, PHt, noise) -> x (bytes of NX float64)
 * or None when S is singular (motion.py's MotionFilter.correct). */
static PyObject *filter_correct(PyObject *self, PyObject *args) {
    PyObject *o[11];
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10]))
        return NULL;
    buf_t b[11];
    memset(b, 0, sizeof b);
    PyObject *res = NULL;
    double x[NX];
    if (!get_state(o, b, x)) goto done;
    static const char *what[] = {"y", "H", "S", "PHt", "noise"};
    const Py_ssize_t size[] = {6, 6 * NS, 36, NS * 6, 36};
    for (int i = 6; i < 11; i++)
        if (!get(o[i], size[i - 6], &b[i], what[i - 6])) goto done;
    res = correct(x, b[6].view.buf, b[7].view.buf, b[8].view.buf, b[9].view.buf,
                  b[10].view.buf)
          ? PyBytes_FromStringAndSize((const char *)x, sizeof x) : Py_NewRef(Py_None);
done:
    release(b, 11);
    return res;
}

/* filter_mix(p, R, v, omega, a, P, p2, R2, v2, omega2, a2, P2, w, w2) -> x (bytes of NX
 * float64): two states mixed about the first (motion.py's MotionFilter.mix). */
static PyObject *filter_mix(PyObject *self, PyObject *args) {
    PyObject *o[12];
    double w, w2;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOdd", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &w, &w2))
        return NULL;
    buf_t b[12];
    memset(b, 0, sizeof b);
    PyObject *res = NULL;
    double x[NX], x2[NX];
    if (!get_state(o, b, x) || !get_state(o + 6, b + 6, x2)) goto done;
    mix(x, x2, w, w2);
    res = PyBytes_FromStringAndSize((const char *)x, sizeof x);
done:
    release(b, 12);
    return res;
}

/* One model's prediction and innovation in imm_update: its pose moved dt ahead (when
 * dt > 0) and innovate(). */
static int model_innovation(double x[NX], double dt, const double *Q, const double *pm,
                            const double *Rm, const double *H, const double *noise,
                            const double *mo, double y[6], double S[36], double PHt[NS * 6],
                            double *nis, double *logdet) {
    double W[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    if (dt > 0.0) {
        double r[3], Rn[9];
        for (int i = 0; i < 3; i++) {
            r[i] = x[15 + i] * dt;
            x[i] = x[i] + x[12 + i] * dt + 0.5 * dt * dt * x[18 + i];
        }
        rodrigues(r, W);
        matmul3(W, x + 3, Rn);
        memcpy(x + 3, Rn, sizeof Rn);
    } else {
        dt = 0.0;
    }
    return innovate(x, W, dt, Q, pm, Rm, H, noise, mo, y, S, PHt, nis, logdet);
}

/* imm_update(x_smooth, x_quick, Q_smooth, Q_quick, t_smooth, t_quick, t_mixed, t, mu,
 *            switch_rate, p_meas, R_meas, H, noise, motion, gate)
 *   -> (x_smooth, x_quick, x_mixed, mu, nis, accepted) or None when a covariance is
 *   singular: motion.py's ImmFilter.update on state blocks (NX float64 each; mu 2): the
 *   models' interaction, each model's prediction to t (Q its process noise over t less
 *   its time) and innovation, the measurement refused when both chi-squares are above
 *   the gate (mu then the prior), else the models' probabilities by their likelihoods
 *   and both corrected; the mixture about the likelier model. */
static PyObject *imm_update(PyObject *self, PyObject *args) {
    PyObject *o[16];
    double ts, tq, tm, t, rate, gate;
    if (!PyArg_ParseTuple(args, "OOOOddddOdOOOOOd", &o[0], &o[1], &o[2], &o[3], &ts, &tq,
                          &tm, &t, &o[8], &rate, &o[10], &o[11], &o[12], &o[13], &o[14],
                          &gate))
        return NULL;
    buf_t b[16];
    memset(b, 0, sizeof b);
    PyObject *res = NULL;
    static const char *what[] = {"x_smooth", "x_quick", "Q_smooth", "Q_quick", "", "", "",
                                 "", "mu", "", "p_meas", "R_meas", "H", "noise", "motion"};
    const Py_ssize_t size[] = {NX, NX, NS * NS, NS * NS, 0, 0, 0, 0, 2, 0, 3, 9, 6 * NS, 36, 9};
    for (int i = 0; i < 15; i++) {
        if ((i >= 4 && i <= 7) || i == 9 || (i == 14 && o[14] == Py_None)) continue;
        if (!get(o[i], size[i], &b[i], what[i])) goto done;
    }
    double xs[NX], xq[NX], xm[NX];
    memcpy(xs, b[0].view.buf, sizeof xs);
    memcpy(xq, b[1].view.buf, sizeof xq);
    const double *mu = b[8].view.buf, *pm = b[10].view.buf, *Rm = b[11].view.buf,
                 *H = b[12].view.buf, *noise = b[13].view.buf;
    const double *mo = o[14] == Py_None ? NULL : b[14].view.buf;
    /* interaction: the smooth model starts from the mixture the switching makes */
    double dtm = t - tm > 0.0 ? t - tm : 0.0;
    double s = -expm1(-rate * dtm);
    double sw[2][2] = {{1.0 - s, s}, {s, 1.0 - s}};
    double prior[2], out[2];
    for (int j = 0; j < 2; j++) prior[j] = mu[0] * sw[0][j] + mu[1] * sw[1][j];
    double den = prior[0] > 1e-300 ? prior[0] : 1e-300;
    mix(xs, xq, mu[0] * sw[0][0] / den, mu[1] * sw[1][0] / den);
    double y[2][6], S[2][36], PHt[2][NS * 6], nis[2], logdet[2];
    if (!model_innovation(xs, t - ts, b[2].view.buf, pm, Rm, H, noise, mo, y[0], S[0], PHt[0],
                          &nis[0], &logdet[0])
        || !model_innovation(xq, t - tq, b[3].view.buf, pm, Rm, H, noise, mo, y[1], S[1],
                             PHt[1], &nis[1], &logdet[1])) {
        res = Py_NewRef(Py_None);
        goto done;
    }
    double least = nis[0] < nis[1] ? nis[0] : nis[1];
    int accepted = !(least > gate);
    if (accepted) {
        double ll[2], w[2];
        for (int i = 0; i < 2; i++) ll[i] = -0.5 * (nis[i] + logdet[i]);
        double top = ll[0] > ll[1] ? ll[0] : ll[1];
        for (int i = 0; i < 2; i++) w[i] = prior[i] * exp(ll[i] - top);
        for (int i = 0; i < 2; i++) out[i] = w[i] / (w[0] + w[1]);
        if (!correct(xs, y[0], H, S[0], PHt[0], noise)
            || !correct(xq, y[1], H, S[1], PHt[1], noise)) {
            res = Py_NewRef(Py_None);
            goto done;
        }
    } else {
        out[0] = prior[0];
        out[1] = prior[1];
    }
    int k = out[1] > out[0];   /* numpy's argmax: the first of equals */
    memcpy(xm, k ? xq : xs, sizeof xm);
    mix(xm, k ? xs : xq, out[k], out[1 - k]);
    res = Py_BuildValue("(y#y#y#(dd)di)", (const char *)xs, (Py_ssize_t)sizeof xs,
                        (const char *)xq, (Py_ssize_t)sizeof xq, (const char *)xm,
                        (Py_ssize_t)sizeof xm, out[0], out[1], least, accepted);
done:
    release(b, 16);
    return res;
}

static PyMethodDef methods[] = {
    {"imm_update", imm_update, METH_VARARGS,
     "The two-model filter's update on its models' state blocks, or None."},
    {"filter_mix", filter_mix, METH_VARARGS,
     "Two motion filter states mixed about the first (an interacting multiple model's)."},
    {"filter_innovation", filter_innovation, METH_VARARGS,
     "The motion filter's prediction and a pose measurement's innovation, or None."},
    {"filter_correct", filter_correct, METH_VARARGS,
     "The motion filter's state corrected by an innovation, or None."},
    {"gauss_newton", gauss_newton, METH_VARARGS,
     "A body's pose by Gauss-Newton steps on its stacked marker images, or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fit", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__fit(void) { return uma_twin_module(&module); }
