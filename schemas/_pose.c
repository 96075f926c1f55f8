/* The compiled twin of schemas/codec.py's decode_pose() for the one common case: a pose6d
 * message of floats, with or without a sequence number and a covariance, and nothing else.
 * It reads the msgpack bytes itself and checks what decode_measurement() checks, with the
 * same arithmetic in the same order (the quaternion's norm, the covariance's Gershgorin
 * bound).  Anything else (another type, an unknown or repeated field, an integer where a
 * float is usual, a value the Python decoder would refuse, a covariance that needs the
 * Cholesky test) returns None, and the caller decodes in Python, which accepts it or raises
 * the precise error: errors are made in one place.  Optional: when this does not build,
 * schemas.codec decodes in pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define NCOV 21

/* codec.MAX_MESSAGE_BYTES, schemas.quaternion.QUAT_NORM_TOL and codec.PSD_TOL, given by
 * schemas.codec at import (configure): defined once, there; nothing is decoded before */
static Py_ssize_t MAX_MESSAGE_BYTES = 0;
static double QUAT_NORM_TOL = 0.0, PSD_TOL = 0.0;

typedef struct { const unsigned char *p, *end; } reader_t;

enum { T_INT, T_UINT, T_FLOAT, T_NIL, T_ARRAY, T_STR, T_OTHER };

typedef struct {
    int type;
    int64_t i;   /* T_INT */
    uint64_t u;  /* T_UINT */
    double f;    /* T_FLOAT */
    uint32_t n;  /* T_ARRAY: length, T_STR: length */
    const unsigned char *s; /* T_STR */
} value_t;

static int need(reader_t *r, size_t n) { return (size_t)(r->end - r->p) >= n; }

static uint64_t be(const unsigned char *p, int n) {
    uint64_t v = 0;
    for (int k = 0; k < n; k++) v = (v << 8) | p[k];
    return v;
}

/* One scalar, array header or string; 0 on truncated or unsupported input. */
static int next(reader_t *r, value_t *v) {
    if (!need(r, 1)) return 0;
    unsigned char c = *r->p++;
    int n = 0;
    if (c <= 0x7f) { v->type = T_UINT; v->u = c; return 1; }
    if (c >= 0xe0) { v->type = T_INT; v->i = (int8_t)c; return 1; }
    if (c >= 0x90 && c <= 0x9f) { v->type = T_ARRAY; v->n = c & 0x0f; return 1; }
    if (c >= 0xa0 && c <= 0xbf) {
        v->type = T_STR; v->n = c & 0x1f;
        if (!need(r, v->n)) return 0;
        v->s = r->p; r->p += v->n; return 1;
    }
    switch (c) {
    case 0xc0: v->type = T_NIL; return 1;
    case 0xcc: n = 1; break;
    case 0xcd: n = 2; break;
    case 0xce: n = 4; break;
    case 0xcf: n = 8; break;
    case 0xd0: case 0xd1: case 0xd2: case 0xd3: {
        n = 1 << (c - 0xd0);
        if (!need(r, n)) return 0;
        uint64_t u = be(r->p, n);
        r->p += n;
        v->type = T_INT;
        if (n == 1) v->i = (int8_t)u;
        else if (n == 2) v->i = (int16_t)u;
        else if (n == 4) v->i = (int32_t)u;
        else v->i = (int64_t)u;
        return 1;
    }
    case 0xca: {
        if (!need(r, 4)) return 0;
        uint32_t u = (uint32_t)be(r->p, 4);
        float f;
        memcpy(&f, &u, 4);
        r->p += 4; v->type = T_FLOAT; v->f = f; return 1;
    }
    case 0xcb: {
        if (!need(r, 8)) return 0;
        uint64_t u = be(r->p, 8);
        double d;
        memcpy(&d, &u, 8);
        r->p += 8; v->type = T_FLOAT; v->f = d; return 1;
    }
    case 0xdc: case 0xdd: {
        n = c == 0xdc ? 2 : 4;
        if (!need(r, n)) return 0;
        v->type = T_ARRAY; v->n = (uint32_t)be(r->p, n); r->p += n; return 1;
    }
    default:
        v->type = T_OTHER; return 0; /* bools, maps, bins, ...: Python decides */
    }
    if (!need(r, n)) return 0;
    v->type = T_UINT; v->u = be(r->p, n); r->p += n;
    return 1;
}

/* A non-negative integer below 2**63 (codec._int_in's range). */
static int int_field(reader_t *r, int64_t *out) {
    value_t v;
    if (!next(r, &v)) return 0;
    if (v.type == T_UINT && v.u < ((uint64_t)1 << 63)) { *out = (int64_t)v.u; return 1; }
    if (v.type == T_INT && v.i >= 0) { *out = v.i; return 1; }
    return 0;
}

/* An array of exactly n finite floats (integers: Python decides). */
static int floats_field(reader_t *r, double *out, uint32_t n) {
    value_t v;
    if (!next(r, &v) || v.type != T_ARRAY || v.n != n) return 0;
    for (uint32_t k = 0; k < n; k++) {
        if (!next(r, &v) || v.type != T_FLOAT || !isfinite(v.f)) return 0;
        out[k] = v.f;
    }
    return 1;
}

/* codec._check_psd's first test, on the packed upper triangle: every variance at least the
 * sum of its row's absolute covariances (plus the tolerance). */
static int gershgorin(const double *c) {
    static const int diag[6] = {0, 6, 11, 15, 18, 20};
    double hi = 1.0, lo = c[0];
    for (int k = 0; k < NCOV; k++) {
        if (c[k] > hi) hi = c[k];
        if (c[k] < lo) lo = c[k];
    }
    if (-lo > hi) hi = -lo;
    double tol = PSD_TOL * hi;
    for (int i = 0; i < 6; i++) {
        double s = 0.0;
        for (int j = 0; j < 6; j++) {
            if (j == i) continue;
            int a = i < j ? i : j, b = i < j ? j : i;
            s += fabs(c[diag[a] + (b - a)]);
        }
        if (!(c[diag[i]] + tol >= s)) return 0;
    }
    return 1;
}

static PyObject *floats_tuple(const double *v, int n) {
    PyObject *t = PyTuple_New(n);
    if (t == NULL) return NULL;
    for (int k = 0; k < n; k++) {
        PyObject *f = PyFloat_FromDouble(v[k]);
        if (f == NULL) { Py_DECREF(t); return NULL; }
        PyTuple_SET_ITEM(t, k, f);
    }
    return t;
}

/* One field's value (after its key), into the decoded parts; 0: Python decides. */
static int field(reader_t *r, char name, int64_t *ints, double *p, double *q, double *c,
                 int *has_c) {
    value_t v;
    switch (name) {
    case 'v': return int_field(r, &ints[0]) && ints[0] == 1;
    case 'k': return next(r, &v) && v.type == T_STR && v.n == 6 && memcmp(v.s, "pose6d", 6) == 0;
    case 't': return int_field(r, &ints[1]);
    case 's': return int_field(r, &ints[2]);
    case 'p': return floats_field(r, p, 3);
    case 'q': return floats_field(r, q, 4);
    case 'c':
        if (need(r, 1) && *r->p == 0xc0) { r->p++; return 1; }
        return (*has_c = floats_field(r, c, NCOV));
    }
    return 0;
}

#define REQUIRED 0x37 /* v k t p q (bits of "vktspqc") */

/* decode(data) -> (t, seq or None, (px, py, pz), (qx, qy, qz, qw), 21 floats or None),
 * or None: decode it in Python. */
static PyObject *decode(PyObject *self, PyObject *arg) {
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) {
        PyErr_Clear();
        Py_RETURN_NONE;
    }
    reader_t r = {(const unsigned char *)view.buf, (const unsigned char *)view.buf + view.len};
    int64_t ints[3] = {-1, -1, -1}; /* v, t, s */
    double p[3], q[4], c[NCOV];
    int seen = 0, has_c = 0;
    int ok = view.len > 0 && view.len <= MAX_MESSAGE_BYTES && *r.p >= 0x80 && *r.p <= 0x8f;
    uint32_t fields = ok ? (uint32_t)(*r.p++ & 0x0f) : 0;
    for (uint32_t k = 0; ok && k < fields; k++) {
        value_t key;
        const char *names = "vktspqc", *at;
        ok = next(&r, &key) && key.type == T_STR && key.n == 1
             && (at = memchr(names, key.s[0], 7)) != NULL && !(seen & (1 << (at - names)));
        if (!ok) break;
        seen |= 1 << (at - names);
        ok = field(&r, key.s[0], ints, p, q, c, &has_c);
    }
    ok = ok && (seen & REQUIRED) == REQUIRED && r.p == r.end;
    PyBuffer_Release(&view);
    if (!ok) Py_RETURN_NONE;
    double x = q[0], y = q[1], z = q[2], w = q[3];
    double n = sqrt(x * x + y * y + z * z + w * w);
    if (fabs(n - 1.0) > QUAT_NORM_TOL) Py_RETURN_NONE;
    double qn[4] = {x / n, y / n, z / n, w / n};
    if (has_c) {
        static const int diag[6] = {0, 6, 11, 15, 18, 20};
        for (int i = 0; i < 6; i++)
            if (c[diag[i]] < 0) Py_RETURN_NONE;
        if (!gershgorin(c)) Py_RETURN_NONE;
    }
    PyObject *pt = floats_tuple(p, 3), *qt = floats_tuple(qn, 4);
    PyObject *ct = has_c ? floats_tuple(c, NCOV) : Py_NewRef(Py_None);
    PyObject *st = ints[2] >= 0 ? PyLong_FromLongLong(ints[2]) : Py_NewRef(Py_None);
    PyObject *tt = PyLong_FromLongLong(ints[1]);
    PyObject *out = pt && qt && ct && st && tt ? PyTuple_Pack(5, tt, st, pt, qt, ct) : NULL;
    Py_XDECREF(pt);
    Py_XDECREF(qt);
    Py_XDECREF(ct);
    Py_XDECREF(st);
    Py_XDECREF(tt);
    return out;
}

static PyObject *configure(PyObject *self, PyObject *args) {
    if (!PyArg_ParseTuple(args, "ndd", &MAX_MESSAGE_BYTES, &QUAT_NORM_TOL, &PSD_TOL))
        return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"configure", configure, METH_VARARGS,
     "configure(max_message_bytes, quat_norm_tol, psd_tol): the codec's limits"},
    {"decode", decode, METH_O,
     "decode(data) -> (t, seq, position, quaternion, covariance) or None (decode in Python)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_pose", NULL, -1, methods};

PyMODINIT_FUNC PyInit__pose(void) { return PyModule_Create(&module); }
