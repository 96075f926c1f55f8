/* The compiled twin of services/outside_in/pose.py's _gauss_newton: a body's pose fitted
 * to its stacked marker images by Gauss-Newton steps (each a left perturbation of the
 * pose, relinearised where it lands), with the Jacobian at the solution.
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

/* A x = b for 6 x 6 A by LU with partial pivoting (A and b overwritten); 0 when singular. */
static int solve6(double A[36], double b[6]) {
    for (int c = 0; c < 6; c++) {
        int piv = c;
        for (int i = c + 1; i < 6; i++)
            if (fabs(A[6 * i + c]) > fabs(A[6 * piv + c])) piv = i;
        if (A[6 * piv + c] == 0.0) return 0;
        if (piv != c) {
            for (int j = 0; j < 6; j++) {
                double t = A[6 * c + j]; A[6 * c + j] = A[6 * piv + j]; A[6 * piv + j] = t;
            }
            double t = b[c]; b[c] = b[piv]; b[piv] = t;
        }
        for (int i = c + 1; i < 6; i++) {
            double f = A[6 * i + c] / A[6 * c + c];
            for (int j = c; j < 6; j++) A[6 * i + j] -= f * A[6 * c + j];
            b[i] -= f * b[c];
        }
    }
    for (int i = 5; i >= 0; i--) {
        double v = b[i];
        for (int j = i + 1; j < 6; j++) v -= A[6 * i + j] * b[j];
        b[i] = v / A[6 * i + i];
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
        if (!solve6(A, g)) return 0;
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

static PyMethodDef methods[] = {
    {"gauss_newton", gauss_newton, METH_VARARGS,
     "A body's pose by Gauss-Newton steps on its stacked marker images, or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fit", NULL, -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__fit(void) { return PyModule_Create(&module); }
