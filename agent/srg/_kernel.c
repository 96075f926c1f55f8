/* The compiled twin of agent/srg/kernel.py's evaluate(): the same operations in the same
 * order, on the same data (the buffers' Python lists), without the interpreter's cost per
 * float operation.  It returns None wherever the Python kernel would raise (an edge with
 * no value at t, or anything unexpected), so errors are made in one place: the caller then
 * runs the Python kernel, which raises the precise error.  Optional: when this does not
 * build, agent.srg.kernel runs in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>

#define SMALL_ANGLE 1e-8 /* geometry._SMALL_ANGLE */

typedef struct { double v[7]; } pose_t; /* px py pz qx qy qz qw */

/* Hamilton product a * b of xyzw quaternions. */
static void quat_mul(const double *a, const double *b, double *out) {
    double ax = a[0], ay = a[1], az = a[2], aw = a[3];
    double bx = b[0], by = b[1], bz = b[2], bw = b[3];
    out[0] = aw * bx + ax * bw + ay * bz - az * by;
    out[1] = aw * by - ax * bz + ay * bw + az * bx;
    out[2] = aw * bz + ax * by - ay * bx + az * bw;
    out[3] = aw * bw - ax * bx - ay * by - az * bz;
}

/* v + w t + u x t with t = 2 u x v. */
static void rotate(const double *q, const double *v, double *out) {
    double x = q[0], y = q[1], z = q[2], w = q[3];
    double tx = 2.0 * (y * v[2] - z * v[1]);
    double ty = 2.0 * (z * v[0] - x * v[2]);
    double tz = 2.0 * (x * v[1] - y * v[0]);
    out[0] = v[0] + w * tx + (y * tz - z * ty);
    out[1] = v[1] + w * ty + (z * tx - x * tz);
    out[2] = v[2] + w * tz + (x * ty - y * tx);
}

static void compose(const pose_t *a, const pose_t *b, pose_t *out) {
    double r[3], q[4];
    rotate(a->v + 3, b->v, r);
    quat_mul(a->v + 3, b->v + 3, q);
    out->v[0] = a->v[0] + r[0];
    out->v[1] = a->v[1] + r[1];
    out->v[2] = a->v[2] + r[2];
    memcpy(out->v + 3, q, sizeof q);
}

static void inverse(pose_t *p) {
    double q[4] = {-p->v[3], -p->v[4], -p->v[5], p->v[6]}, r[3];
    rotate(q, p->v, r);
    p->v[0] = -r[0];
    p->v[1] = -r[1];
    p->v[2] = -r[2];
    memcpy(p->v + 3, q, sizeof q);
}

/* Rotation vector of q0^-1 q1 (slerp's log). */
static void log_between(const pose_t *a, const pose_t *b, double *out) {
    double c[4] = {-a->v[3], -a->v[4], -a->v[5], a->v[6]}, d[4];
    quat_mul(c, b->v + 3, d);
    if (d[3] < 0) {
        d[0] = -d[0]; d[1] = -d[1]; d[2] = -d[2]; d[3] = -d[3];
    }
    double s = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    double k = s < SMALL_ANGLE ? 2.0 / d[3] : 2.0 * atan2(s, d[3]) / s;
    out[0] = d[0] * k; out[1] = d[1] * k; out[2] = d[2] * k;
}

static void interpolate(const pose_t *a, const pose_t *b, const double *delta, double f,
                        pose_t *out) {
    double rx = delta[0] * f, ry = delta[1] * f, rz = delta[2] * f;
    double th = sqrt(rx * rx + ry * ry + rz * rz);
    double k = th < SMALL_ANGLE ? 0.5 - th * th / 48.0 : sin(0.5 * th) / th;
    double e[4] = {rx * k, ry * k, rz * k, cos(0.5 * th)};
    for (int i = 0; i < 3; i++) out->v[i] = a->v[i] + (b->v[i] - a->v[i]) * f;
    quat_mul(a->v + 3, e, out->v + 3);
}

/* A tuple of n floats into out; 0 on anything else (no exception left set). */
static int read_floats(PyObject *tuple, double *out, Py_ssize_t n) {
    if (!PyTuple_Check(tuple) || PyTuple_GET_SIZE(tuple) != n) return 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *x = PyTuple_GET_ITEM(tuple, i);
        if (!PyFloat_CheckExact(x)) return 0;
        out[i] = PyFloat_AS_DOUBLE(x);
    }
    return 1;
}

static PyObject *float_tuple(const double *v, Py_ssize_t n) {
    PyObject *t = PyTuple_New(n);
    if (t == NULL) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *x = PyFloat_FromDouble(v[i]);
        if (x == NULL) { Py_DECREF(t); return NULL; }
        PyTuple_SET_ITEM(t, i, x);
    }
    return t;
}

static int time_at(PyObject *times, Py_ssize_t i, long long *out) {
    *out = PyLong_AsLongLong(PyList_GET_ITEM(times, i));
    return !(*out == -1 && PyErr_Occurred());
}

/* SampleBuffer.bracket without its errors: 1 found, 0 undefined at t (or unreadable). */
static int bracket(PyObject *times, long long t, long long buffer_ns, double limit,
                   Py_ssize_t *i0, Py_ssize_t *i1, double *f, double *ex) {
    Py_ssize_t n = PyList_GET_SIZE(times);
    long long last, first, t0, t1;
    *f = 0.0;
    *ex = 0.0;
    if (n == 0 || !time_at(times, n - 1, &last)) return 0;
    if (t >= last) {
        *i0 = *i1 = n - 1;
        if (t == last) return 1;
        *ex = (double)(t - last) * 1e-9;
        if (*ex > limit) return 0;
        if (n == 1) { *i0 = *i1 = 0; return 1; }
        if (!time_at(times, n - 2, &t0)) return 0;
        *i0 = n - 2;
        *f = (double)(t - t0) / (double)(last - t0);
        return 1;
    }
    if (!time_at(times, 0, &first) || t < last - buffer_ns) return 0;
    if (t <= first) {
        *i0 = *i1 = 0;
        if (t == first) return 1;
        *ex = (double)(first - t) * 1e-9;
        if (*ex > limit) return 0;
        if (n == 1) return 1;
        if (!time_at(times, 1, &t1)) return 0;
        *i1 = 1;
        *f = (double)(t - first) / (double)(t1 - first);
        return 1;
    }
    Py_ssize_t lo = 0, hi = n; /* bisect_left */
    while (lo < hi) {
        Py_ssize_t mid = (lo + hi) / 2;
        long long tm;
        if (!time_at(times, mid, &tm)) return 0;
        if (tm < t) lo = mid + 1; else hi = mid;
    }
    if (!time_at(times, lo, &t1)) return 0;
    *i0 = *i1 = lo;
    if (t1 == t) return 1;
    if (!time_at(times, lo - 1, &t0)) return 0;
    *i0 = lo - 1;
    *f = (double)(t - t0) / (double)(t1 - t0);
    return 1;
}

/* What the walk along a chain leaves of each item: the composed pose after it and, for a
 * measured edge, its value as sampled (before an inversion) and its bracket. */
typedef struct {
    pose_t after, sampled;
    Py_ssize_t i0, i1;
    double f;
} step_t;

/* Chains longer than this are left to the Python kernel. */
#define MAX_ITEMS 64

/* One measured edge at t: its value as sampled into step->sampled, its bracket into step;
 * its stamps appended.  1 done, 0 undefined, -1 a Python error. */
static int measured(PyObject *entry, long long t, step_t *step, double *extrapolated,
                    PyObject *stamps) {
    pose_t *value = &step->sampled;
    PyObject *times = PyTuple_GET_ITEM(entry, 1), *values = PyTuple_GET_ITEM(entry, 2);
    PyObject *deltas = PyTuple_GET_ITEM(entry, 3);
    if (!PyList_CheckExact(times) || !PyList_CheckExact(values) || !PyList_CheckExact(deltas))
        return 0;
    long long buffer_ns = PyLong_AsLongLong(PyTuple_GET_ITEM(entry, 4));
    double limit = PyFloat_AsDouble(PyTuple_GET_ITEM(entry, 5));
    if (PyErr_Occurred()) { PyErr_Clear(); return 0; }
    Py_ssize_t i0, i1;
    double f, ex;
    if (!bracket(times, t, buffer_ns, limit, &i0, &i1, &f, &ex)) { PyErr_Clear(); return 0; }
    Py_ssize_t n = PyList_GET_SIZE(values);
    if (i1 >= n || PyList_GET_SIZE(deltas) != n) return 0;
    pose_t v0, v1;
    if (!read_floats(PyList_GET_ITEM(values, i0), v0.v, 7)) return 0;
    if (i0 == i1) {
        *value = v0;
    } else {
        double delta[3];
        if (!read_floats(PyList_GET_ITEM(values, i1), v1.v, 7)) return 0;
        PyObject *cached = PyList_GET_ITEM(deltas, i0);
        if (cached == Py_None) {
            log_between(&v0, &v1, delta);
            PyObject *d = float_tuple(delta, 3);
            if (d == NULL) return -1;
            PyList_SetItem(deltas, i0, d); /* steals d */
        } else if (!read_floats(cached, delta, 3)) {
            return 0;
        }
        interpolate(&v0, &v1, delta, f, value);
    }
    if (ex > *extrapolated) *extrapolated = ex;
    step->i0 = i0;
    step->i1 = i1;
    step->f = f;
    PyObject *stamp = Py_BuildValue("(OO)", PyList_GET_ITEM(times, i0),
                                    PyList_GET_ITEM(times, i1));
    if (stamp == NULL || PyList_Append(stamps, stamp) < 0) { Py_XDECREF(stamp); return -1; }
    Py_DECREF(stamp);
    return 1;
}

/* The chain at t: every item's step (the composed pose after it, a measured edge's value
 * and bracket), the largest extrapolation, the stamps appended.  1 done, 0 undefined (or
 * anything unexpected: the Python kernel decides), -1 a Python error. */
static int walk(PyObject *t_obj, PyObject *items, step_t *steps, double *extrapolated,
                PyObject *stamps) {
    long long t = 0;
    int have_t = 0;
    Py_ssize_t count = PyTuple_GET_SIZE(items);
    if (count == 0 || count > MAX_ITEMS) return 0;
    for (Py_ssize_t k = 0; k < count; k++) {
        PyObject *entry = PyTuple_GET_ITEM(items, k);
        pose_t value;
        if (!PyTuple_Check(entry)) return 0;
        if (PyTuple_GET_SIZE(entry) == 1) {
            if (!read_floats(PyTuple_GET_ITEM(entry, 0), value.v, 7)) return 0;
        } else {
            if (PyTuple_GET_SIZE(entry) != 7) return 0;
            if (!have_t) {
                t = PyLong_AsLongLong(t_obj); /* None or out of range: the Python kernel */
                if (t == -1 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
                have_t = 1;
            }
            int r = measured(entry, t, &steps[k], extrapolated, stamps);
            if (r <= 0) return r;
            value = steps[k].sampled;
            if (!PyObject_IsTrue(PyTuple_GET_ITEM(entry, 6))) inverse(&value);
        }
        if (k == 0) steps[k].after = value;
        else compose(&steps[k - 1].after, &value, &steps[k].after);
    }
    return 1;
}

/* Write n doubles into a writable contiguous float64 buffer of exactly n (a numpy array,
 * read through the buffer protocol: no numpy headers needed to build). */
static int write_doubles(PyObject *target, const double *v, Py_ssize_t n) {
    Py_buffer view;
    if (PyObject_GetBuffer(target, &view, PyBUF_WRITABLE | PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0)
        return 0;
    int ok = view.itemsize == 8 && view.len == n * 8 && view.format != NULL
             && (strcmp(view.format, "d") == 0 || strcmp(view.format, "<d") == 0);
    if (ok) memcpy(view.buf, v, n * sizeof(double));
    PyBuffer_Release(&view);
    if (!ok) PyErr_SetString(PyExc_ValueError, "the output must be float64 arrays of 3, 4 or 36");
    return ok;
}

static PyObject *evaluate(PyObject *Py_UNUSED(self), PyObject *args) {
    PyObject *t_obj, *items, *p_out, *q_out;
    int want_edges;
    if (!PyArg_ParseTuple(args, "OO!pOO", &t_obj, &PyTuple_Type, &items, &want_edges, &p_out,
                          &q_out))
        return NULL;
    step_t steps[MAX_ITEMS];
    double extrapolated = 0.0;
    PyObject *stamps = PyList_New(0), *edges = NULL, *prefixes = NULL;
    if (stamps == NULL) return NULL;
    int r = walk(t_obj, items, steps, &extrapolated, stamps);
    if (r <= 0) goto done;
    Py_ssize_t count = PyTuple_GET_SIZE(items);
    const pose_t *acc = &steps[count - 1].after;
    if (!write_doubles(p_out, acc->v, 3) || !write_doubles(q_out, acc->v + 3, 4)) {
        r = -1;
        goto done;
    }
    if (!want_edges) return Py_BuildValue("(dNOO)", extrapolated, stamps, Py_None, Py_None);
    edges = PyList_New(0);
    prefixes = PyList_New(count);
    if (edges == NULL || prefixes == NULL) { r = -1; goto done; }
    for (Py_ssize_t k = 0; k < count; k++) {
        PyObject *a = float_tuple(steps[k].after.v, 7);
        if (a == NULL) { r = -1; goto done; }
        PyList_SET_ITEM(prefixes, k, a);
        if (PyTuple_GET_SIZE(PyTuple_GET_ITEM(items, k)) == 1) continue;
        PyObject *v = float_tuple(steps[k].sampled.v, 7);
        PyObject *e = v == NULL ? NULL : Py_BuildValue("(nndN)", steps[k].i0, steps[k].i1,
                                                       steps[k].f, v);
        if (e == NULL || PyList_Append(edges, e) < 0) { Py_XDECREF(e); r = -1; goto done; }
        Py_DECREF(e);
    }
    return Py_BuildValue("(dNNN)", extrapolated, stamps, edges, prefixes);
done:
    Py_XDECREF(stamps);
    Py_XDECREF(edges);
    Py_XDECREF(prefixes);
    if (r < 0) return NULL;
    Py_RETURN_NONE;
}

/* Read a C-contiguous float64 buffer of exactly n doubles (a numpy array); 0 if it is not
 * one (no Python error left set: the caller falls back to numpy). */
static int read_doubles(PyObject *source, double *out, Py_ssize_t n) {
    Py_buffer view;
    if (PyObject_GetBuffer(source, &view, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyErr_Clear();
        return 0;
    }
    int ok = view.itemsize == 8 && view.len == n * 8 && view.format != NULL
             && (strcmp(view.format, "d") == 0 || strcmp(view.format, "<d") == 0);
    if (ok) memcpy(out, view.buf, n * sizeof(double));
    PyBuffer_Release(&view);
    return ok;
}

/* out += Ad C Ad^T, Ad = [[R, [p]x R], [0, R]] the SE(3) adjoint of pose (p, q). */
static void add_mapped(const double *pose, const double *C, double *out) {
    double x = pose[3], y = pose[4], z = pose[5], w = pose[6], R[9], Ad[36] = {0}, T[36];
    R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - z * w); R[2] = 2 * (x * z + y * w);
    R[3] = 2 * (x * y + z * w); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - x * w);
    R[6] = 2 * (x * z - y * w); R[7] = 2 * (y * z + x * w); R[8] = 1 - 2 * (x * x + y * y);
    const double px = pose[0], py = pose[1], pz = pose[2];
    const double S[9] = {0, -pz, py, pz, 0, -px, -py, px, 0};
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            Ad[i * 6 + j] = Ad[(i + 3) * 6 + j + 3] = R[i * 3 + j];
            Ad[i * 6 + j + 3] = S[i * 3] * R[j] + S[i * 3 + 1] * R[3 + j] + S[i * 3 + 2] * R[6 + j];
        }
    for (int i = 0; i < 6; i++) /* T = Ad C */
        for (int j = 0; j < 6; j++) {
            double s = 0;
            for (int k = 0; k < 6; k++) s += Ad[i * 6 + k] * C[k * 6 + j];
            T[i * 6 + j] = s;
        }
    for (int i = 0; i < 6; i++) /* out += T Ad^T */
        for (int j = 0; j < 6; j++) {
            double s = 0;
            for (int k = 0; k < 6; k++) s += T[i * 6 + k] * Ad[j * 6 + k];
            out[i * 6 + j] += s;
        }
}

static PyObject *propagate(PyObject *Py_UNUSED(self), PyObject *args) {
    PyObject *poses, *mats, *out;
    if (!PyArg_ParseTuple(args, "O!O!O", &PyList_Type, &poses, &PyList_Type, &mats, &out))
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(poses);
    if (n != PyList_GET_SIZE(mats)) Py_RETURN_FALSE;
    double acc[36] = {0}, pose[7], C[36];
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!read_floats(PyList_GET_ITEM(poses, i), pose, 7)
            || !read_doubles(PyList_GET_ITEM(mats, i), C, 36))
            Py_RETURN_FALSE;
        add_mapped(pose, C, acc);
    }
    if (!write_doubles(out, acc, 36)) return NULL;
    Py_RETURN_TRUE;
}

/* A measured edge's covariance at its bracket into C, as plan.Chain._edge_cov takes it:
 * its samples' (interpolated between two, never extrapolated), else the edge's own (spec:
 * (covs, kind, matrix), kind 0 none, 1 an SE(3) one, 2 a decoupled one to move to the
 * edge's translation).  Returns the kind of C (0 none, 1 SE(3), 2 decoupled), -1: the
 * Python path decides. */
static int edge_covariance(PyObject *spec, const step_t *step, double *C) {
    if (!PyTuple_Check(spec) || PyTuple_GET_SIZE(spec) != 3) return -1;
    PyObject *covs = PyTuple_GET_ITEM(spec, 0);
    if (!PyList_CheckExact(covs) || step->i1 >= PyList_GET_SIZE(covs)) return -1;
    PyObject *c0 = PyList_GET_ITEM(covs, step->i0), *c1 = PyList_GET_ITEM(covs, step->i1);
    if (c0 != Py_None && c1 != Py_None) {
        double a = step->f < 0.0 ? 0.0 : step->f > 1.0 ? 1.0 : step->f, D[36];
        if (!read_doubles(c0, C, 36)) return -1;
        if (c0 == c1 || a == 0.0) return 1;
        if (!read_doubles(c1, D, 36)) return -1;
        for (int k = 0; k < 36; k++) C[k] = C[k] + (D[k] - C[k]) * a;
        return 1;
    }
    if (c0 != Py_None || c1 != Py_None) return read_doubles(c0 != Py_None ? c0 : c1, C, 36) ? 1 : -1;
    long kind = PyLong_AsLong(PyTuple_GET_ITEM(spec, 1));
    if (kind < 0 || kind > 2) { PyErr_Clear(); return -1; }
    if (kind == 0) return 0;
    return read_doubles(PyTuple_GET_ITEM(spec, 2), C, 36) ? (int)kind : -1;
}

/* evaluate_covariance(t_ns, items, cov_items, p_out, q_out, cov_out): evaluate() and the
 * chain's covariance (plan.Chain._covariance) in one call: each item's covariance mapped by
 * the composed pose before it (after it, for an edge walked backwards; a decoupled one
 * through the edge's translation first) and summed into cov_out.  cov_items holds, per
 * item, (covariance or None,) for a constant and the spec of edge_covariance for a
 * measured edge.  Returns (extrapolated_s, stamps, has_covariance), or None: the Python
 * path decides. */
static PyObject *evaluate_covariance(PyObject *Py_UNUSED(self), PyObject *args) {
    PyObject *t_obj, *items, *cov_items, *p_out, *q_out, *cov_out;
    if (!PyArg_ParseTuple(args, "OO!O!OOO", &t_obj, &PyTuple_Type, &items, &PyTuple_Type,
                          &cov_items, &p_out, &q_out, &cov_out))
        return NULL;
    Py_ssize_t count = PyTuple_GET_SIZE(items);
    if (PyTuple_GET_SIZE(cov_items) != count) Py_RETURN_NONE;
    step_t steps[MAX_ITEMS];
    double extrapolated = 0.0, acc[36] = {0}, C[36];
    const pose_t identity = {{0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0}};
    int terms = 0;
    PyObject *stamps = PyList_New(0);
    if (stamps == NULL) return NULL;
    int r = walk(t_obj, items, steps, &extrapolated, stamps);
    if (r <= 0) goto done;
    r = 0;
    for (Py_ssize_t k = 0; k < count; k++) {
        PyObject *entry = PyTuple_GET_ITEM(items, k), *spec = PyTuple_GET_ITEM(cov_items, k);
        const pose_t *before = k ? &steps[k - 1].after : &identity;
        if (PyTuple_GET_SIZE(entry) == 1) {
            if (!PyTuple_Check(spec) || PyTuple_GET_SIZE(spec) != 1) goto done;
            if (PyTuple_GET_ITEM(spec, 0) == Py_None) continue;
            if (!read_doubles(PyTuple_GET_ITEM(spec, 0), C, 36)) goto done;
            add_mapped(before->v, C, acc);
            terms++;
            continue;
        }
        int kind = edge_covariance(spec, &steps[k], C);
        if (kind < 0) goto done;
        if (kind == 0) continue;
        pose_t at = PyObject_IsTrue(PyTuple_GET_ITEM(entry, 6)) ? *before : steps[k].after;
        if (kind == 2) {
            pose_t shift = {{steps[k].sampled.v[0], steps[k].sampled.v[1],
                             steps[k].sampled.v[2], 0.0, 0.0, 0.0, 1.0}}, moved;
            compose(&at, &shift, &moved);
            at = moved;
        }
        add_mapped(at.v, C, acc);
        terms++;
    }
    const pose_t *pose = &steps[count - 1].after;
    if (!write_doubles(p_out, pose->v, 3) || !write_doubles(q_out, pose->v + 3, 4)
        || (terms && !write_doubles(cov_out, acc, 36))) {
        r = -1;
        goto done;
    }
    return Py_BuildValue("(dNO)", extrapolated, stamps, terms ? Py_True : Py_False);
done:
    Py_DECREF(stamps);
    if (r < 0) return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"evaluate", evaluate, METH_VARARGS,
     "evaluate(t_ns, items, want_edges, p_out, q_out): agent.srg.kernel.evaluate "
     "compiled; None where it would raise."},
    {"evaluate_covariance", evaluate_covariance, METH_VARARGS,
     "evaluate_covariance(t_ns, items, cov_items, p_out, q_out, cov_out): evaluate with the "
     "chain's covariance; None where the Python path decides."},
    {"propagate", propagate, METH_VARARGS,
     "propagate(poses, covariances, out): agent.srg.kernel.propagate compiled into out "
     "(6x6 float64); False where an input is not a 7-float tuple or a 6x6 float64 array."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernel", NULL, -1, methods,
                                     NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernel(void) { return uma_twin_module(&module); }
