/* The compiled twin of agent/protocol/query.py's pose_from_wire() for the one common case:
 * an answer as an agent writes it (every field present, floats and integers where numbers
 * go, ids already seen valid, flat attributes).  It checks what the Python reader checks,
 * with the same arithmetic (the quaternion's norm and renormalisation), and builds the same
 * values.  Anything else (a missing or unknown field, a bool or a string where a number
 * goes, an id not seen before, a nested attribute, a value the reader would refuse) returns
 * None, and the caller reads the answer in Python, which accepts it or raises the precise
 * error: errors are made in one place.  Optional: when this does not build, the reader runs
 * in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
#include <math.h>
#include <string.h>

/* schemas.quaternion.QUAT_NORM_TOL and query._INF_WHEN_NONE, given at import (configure):
 * defined once, there; nothing is read before */
static double QUAT_NORM_TOL = 0.0;
static PyObject *INF_WHEN_NONE = NULL; /* a tuple of str */

#define NFIELDS 10
static const char *FIELDS[NFIELDS] = {"source", "target", "t_ns", "position", "quaternion",
                                      "covariance", "path", "edges", "attributes",
                                      "extrapolated_s"};
enum { F_SOURCE, F_TARGET, F_T, F_POSITION, F_QUATERNION, F_COVARIANCE, F_PATH, F_EDGES,
       F_ATTRIBUTES, F_EXTRAPOLATED };

/* A finite float or int (not a bool) as a double; 0: Python decides. */
static int number(PyObject *x, double *out) {
    if (PyFloat_CheckExact(x)) *out = PyFloat_AS_DOUBLE(x);
    else if (PyLong_CheckExact(x)) {
        *out = PyLong_AsDouble(x); /* rounded as float(int) rounds */
        if (*out == -1.0 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
    } else return 0;
    return isfinite(*out);
}

/* n numbers from a list of exactly n; 0: Python decides. */
static int numbers(PyObject *x, double *out, Py_ssize_t n) {
    if (!PyList_CheckExact(x) || PyList_GET_SIZE(x) != n) return 0;
    for (Py_ssize_t k = 0; k < n; k++)
        if (!number(PyList_GET_ITEM(x, k), out + k)) return 0;
    return 1;
}

/* A str the reader has seen valid (its set of valid ids); 0: Python decides. */
static int known(PyObject *x, PyObject *valid) {
    if (!PyUnicode_CheckExact(x)) return 0;
    int in = PySet_Contains(valid, x);
    if (in < 0) { PyErr_Clear(); return 0; }
    return in;
}

/* An exact int moved by to_local (None: as it is); NULL with an error set if to_local
 * raised, NULL without one: Python decides. */
static PyObject *local_time(PyObject *t, PyObject *to_local) {
    if (!PyLong_CheckExact(t)) return NULL;
    if (to_local == Py_None) { Py_INCREF(t); return t; }
    return PyObject_CallOneArg(to_local, t);
}

/* Fill a float64 buffer of n items; 0 if it is not one (a caller's bug: Python decides). */
static int fill(PyObject *arr, const double *v, Py_ssize_t n) {
    Py_buffer view;
    if (PyObject_GetBuffer(arr, &view, PyBUF_WRITABLE | PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyErr_Clear();
        return 0;
    }
    int ok = view.itemsize == 8 && view.format != NULL && strcmp(view.format, "d") == 0
             && view.len == n * 8;
    if (ok) memcpy(view.buf, v, n * 8);
    PyBuffer_Release(&view);
    return ok;
}

static PyObject *path_of(PyObject *x, PyObject *frames) {
    if (!PyList_CheckExact(x)) return NULL;
    Py_ssize_t n = PyList_GET_SIZE(x);
    for (Py_ssize_t k = 0; k < n; k++)
        if (!known(PyList_GET_ITEM(x, k), frames)) return NULL;
    return PyList_GetSlice(x, 0, n);
}

/* One edge as the reader makes it: parent, child, forward, owner, t_ns (local). */
static PyObject *edge_of(PyObject *e, PyObject *frames, PyObject *agents, PyObject *to_local) {
    if (!PyDict_CheckExact(e) || PyDict_GET_SIZE(e) != 5) return NULL;
    PyObject *parent = PyDict_GetItemString(e, "parent");
    PyObject *child = PyDict_GetItemString(e, "child");
    PyObject *inverted = PyDict_GetItemString(e, "inverted");
    PyObject *owner = PyDict_GetItemString(e, "owner");
    PyObject *t = PyDict_GetItemString(e, "t_ns");
    if (!parent || !child || !inverted || !owner || !t || !known(parent, frames)
        || !known(child, frames) || !PyBool_Check(inverted) || !known(owner, agents))
        return NULL;
    PyObject *local = local_time(t, to_local);
    if (local == NULL) return NULL;
    PyObject *out = Py_BuildValue("{sOsOsOsOsN}", "parent", parent, "child", child, "forward",
                                  inverted == Py_True ? Py_False : Py_True, "owner", owner,
                                  "t_ns", local);
    return out;
}

static PyObject *edges_of(PyObject *x, PyObject *frames, PyObject *agents,
                          PyObject *to_local) {
    if (!PyList_CheckExact(x)) return NULL;
    Py_ssize_t n = PyList_GET_SIZE(x);
    PyObject *out = PyList_New(n);
    if (out == NULL) return NULL;
    for (Py_ssize_t k = 0; k < n; k++) {
        PyObject *e = edge_of(PyList_GET_ITEM(x, k), frames, agents, to_local);
        if (e == NULL) { Py_DECREF(out); return NULL; }
        PyList_SET_ITEM(out, k, e);
    }
    return out;
}

/* Flat attributes (str keys; finite floats, ints, bools, str, None) with an infinite value
 * for each INF_WHEN_NONE name that is None or missing, as attributes_from_wire() makes. */
static PyObject *attributes_of(PyObject *x) {
    if (!PyDict_CheckExact(x)) return NULL;
    Py_ssize_t pos = 0;
    PyObject *k, *v;
    while (PyDict_Next(x, &pos, &k, &v)) {
        if (!PyUnicode_CheckExact(k)) return NULL;
        if (PyFloat_CheckExact(v)) {
            if (!isfinite(PyFloat_AS_DOUBLE(v))) return NULL;
        } else if (v != Py_None && !PyLong_CheckExact(v) && !PyBool_Check(v)
                   && !PyUnicode_CheckExact(v))
            return NULL;
    }
    PyObject *out = PyDict_Copy(x);
    if (out == NULL) return NULL;
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(INF_WHEN_NONE); i++) {
        PyObject *name = PyTuple_GET_ITEM(INF_WHEN_NONE, i);
        PyObject *have = PyDict_GetItem(out, name);
        if (have == NULL || have == Py_None) {
            PyObject *inf = PyFloat_FromDouble(INFINITY);
            if (inf == NULL || PyDict_SetItem(out, name, inf) < 0) {
                Py_XDECREF(inf);
                Py_DECREF(out);
                return NULL;
            }
            Py_DECREF(inf);
        }
    }
    return out;
}

/* The fields' values, each checked; 0: Python decides. */
static int fields_of(PyObject *d, PyObject **f) {
    if (!PyDict_CheckExact(d) || PyDict_GET_SIZE(d) != NFIELDS) return 0;
    for (int k = 0; k < NFIELDS; k++)
        if ((f[k] = PyDict_GetItemString(d, FIELDS[k])) == NULL) return 0;
    return 1;
}

/* The numbers: position, quaternion (renormalised), covariance (or none), extrapolation. */
static int numbers_of(PyObject **f, double *p, double *q, double *cov, int *has_cov,
                      double *extrapolated) {
    if (!numbers(f[F_POSITION], p, 3) || !numbers(f[F_QUATERNION], q, 4)) return 0;
    double x = q[0], y = q[1], z = q[2], w = q[3];
    double n = sqrt(x * x + y * y + z * z + w * w);
    if (fabs(n - 1.0) > QUAT_NORM_TOL) return 0;
    for (int k = 0; k < 4; k++) q[k] /= n;
    *has_cov = f[F_COVARIANCE] != Py_None;
    if (*has_cov && !numbers(f[F_COVARIANCE], cov, 36)) return 0;
    PyObject *e = f[F_EXTRAPOLATED];
    return !PyBool_Check(e) && number(e, extrapolated) && *extrapolated >= 0;
}

/* pose_result(d, frames, agents, to_local, p_out, q_out, cov_out): (path, edges, t_ns,
 * extrapolated_s, attributes, has_covariance) with p_out (3), q_out (4) and cov_out (36)
 * filled, or None: read it in Python. */
static PyObject *pose_result(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *d, *frames, *agents, *to_local, *p_out, *q_out, *cov_out;
    if (!PyArg_ParseTuple(args, "OO!O!OOOO", &d, &PySet_Type, &frames, &PySet_Type, &agents,
                          &to_local, &p_out, &q_out, &cov_out))
        return NULL;
    PyObject *f[NFIELDS];
    double p[3], q[4], cov[36], extrapolated;
    int has_cov;
    if (!fields_of(d, f) || !known(f[F_SOURCE], frames) || !known(f[F_TARGET], frames)
        || !numbers_of(f, p, q, cov, &has_cov, &extrapolated)
        || !fill(p_out, p, 3) || !fill(q_out, q, 4) || (has_cov && !fill(cov_out, cov, 36)))
        Py_RETURN_NONE;
    PyObject *path = NULL, *edges = NULL, *t = NULL, *attributes = NULL;
    if ((path = path_of(f[F_PATH], frames)) == NULL) goto fallback;
    if ((edges = edges_of(f[F_EDGES], frames, agents, to_local)) == NULL) goto fallback;
    if ((t = local_time(f[F_T], to_local)) == NULL) goto fallback;
    if ((attributes = attributes_of(f[F_ATTRIBUTES])) == NULL) goto fallback;
    return Py_BuildValue("(NNNdNO)", path, edges, t, extrapolated, attributes,
                         has_cov ? Py_True : Py_False);
fallback:
    Py_XDECREF(path);
    Py_XDECREF(edges);
    Py_XDECREF(t);
    if (PyErr_Occurred()) return NULL; /* to_local raised: as it would in Python */
    Py_RETURN_NONE;
}

static PyObject *configure(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *names;
    if (!PyArg_ParseTuple(args, "dO!", &QUAT_NORM_TOL, &PyTuple_Type, &names)) return NULL;
    Py_INCREF(names);
    Py_XSETREF(INF_WHEN_NONE, names);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"pose_result", pose_result, METH_VARARGS,
     "pose_result(d, frames, agents, to_local, p_out, q_out, cov_out) -> (path, edges, t_ns, "
     "extrapolated_s, attributes, has_covariance) or None (read it in Python)"},
    {"configure", configure, METH_VARARGS,
     "configure(quat_norm_tol, inf_when_none): the reader's constants"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_wire", NULL, -1, methods};

PyMODINIT_FUNC PyInit__wire(void) { return uma_twin_module(&module); }
