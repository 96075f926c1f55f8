/* The compiled twin of schemas/codec.py's decode_pose() and encode_pose() for the one common
 * case: a pose6d message of floats, with or without a sequence number (and, decoding, a
 * covariance), and nothing else.  Decoding reads the msgpack bytes itself and checks what
 * decode_measurement() checks; encoding checks what encode_pose() checks and writes the
 * bytes msgpack.packb() writes for its map; both with the same arithmetic in the same order
 * (the quaternion's norm, the covariance's Gershgorin bound).  Anything else (another type,
 * an unknown or repeated field, an integer where a float is usual, a value the Python codec
 * would refuse, a covariance that needs the Cholesky test, a covariance to encode) returns
 * None, and the caller does it in Python, which accepts it or raises the precise error:
 * errors are made in one place.  Optional: when this does not build, schemas.codec runs in
 * pure Python. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include "_twin.h"
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

/* ------------------------------------------------------------------ encoding */

typedef struct { unsigned char b[160]; Py_ssize_t n; } out_t;

static void put(out_t *o, const void *p, size_t n) { memcpy(o->b + o->n, p, n); o->n += n; }
static void put1(out_t *o, unsigned char c) { o->b[o->n++] = c; }
static void put_be(out_t *o, uint64_t v, int n) {
    for (int k = n - 1; k >= 0; k--) put1(o, (unsigned char)(v >> (8 * k)));
}

/* A non-negative integer as msgpack-python packs it: the smallest form. */
static void put_uint(out_t *o, uint64_t v) {
    if (v < 128) put1(o, (unsigned char)v);
    else if (v <= 0xff) { put1(o, 0xcc); put_be(o, v, 1); }
    else if (v <= 0xffff) { put1(o, 0xcd); put_be(o, v, 2); }
    else if (v <= 0xffffffffu) { put1(o, 0xce); put_be(o, v, 4); }
    else { put1(o, 0xcf); put_be(o, v, 8); }
}

static void put_double(out_t *o, double d) {
    uint64_t u;
    memcpy(&u, &d, 8);
    put1(o, 0xcb);
    put_be(o, u, 8);
}

/* An exact int (not a bool, not numpy's) in [0, 2**63); 0: Python decides. */
static int int_arg(PyObject *x, int64_t *out) {
    if (!PyLong_CheckExact(x)) return 0;
    int overflow = 0;
    long long v = PyLong_AsLongLongAndOverflow(x, &overflow);
    if (overflow || v < 0 || (v == -1 && PyErr_Occurred())) { PyErr_Clear(); return 0; }
    *out = v;
    return 1;
}

/* n finite numbers from a list or tuple of floats (numpy's float64 is one) and ints, or a
 * 1-D float64 array; 0: Python decides (np.asarray(x, float) there takes more shapes and
 * types). */
static int floats_arg(PyObject *x, double *out, Py_ssize_t n) {
    if (PyList_CheckExact(x) || PyTuple_CheckExact(x)) {
        if (PySequence_Fast_GET_SIZE(x) != n) return 0;
        PyObject **items = PySequence_Fast_ITEMS(x);
        for (Py_ssize_t k = 0; k < n; k++) {
            PyObject *v = items[k];
            if (PyFloat_Check(v)) out[k] = PyFloat_AS_DOUBLE(v); /* numpy float64 too */
            else if (PyLong_CheckExact(v)) {
                out[k] = PyLong_AsDouble(v); /* rounded as float(int) rounds */
                if (out[k] == -1.0 && PyErr_Occurred()) { PyErr_Clear(); return 0; }
            } else return 0;
            if (!isfinite(out[k])) return 0;
        }
        return 1;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(x, &view, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyErr_Clear();
        return 0;
    }
    int ok = view.ndim == 1 && view.itemsize == 8 && view.format != NULL
             && strcmp(view.format, "d") == 0 && view.len == n * 8;
    if (ok) {
        memcpy(out, view.buf, n * 8);
        for (Py_ssize_t k = 0; k < n; k++) ok = ok && isfinite(out[k]);
    }
    PyBuffer_Release(&view);
    return ok;
}

/* encode(t, position, quaternion, seq) -> the pose6d message without a covariance, as
 * codec.encode_pose() makes it, or None: encode it in Python. */
static PyObject *encode(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    int64_t t, seq = -1;
    double p[3], q[4];
    if (nargs != 4 || !int_arg(args[0], &t) || !floats_arg(args[1], p, 3)
        || !floats_arg(args[2], q, 4) || (args[3] != Py_None && !int_arg(args[3], &seq)))
        Py_RETURN_NONE;
    double x = q[0], y = q[1], z = q[2], w = q[3];
    double n = sqrt(x * x + y * y + z * z + w * w);
    if (fabs(n - 1.0) > QUAT_NORM_TOL) Py_RETURN_NONE;
    double qn[4] = {x / n, y / n, z / n, w / n};
    out_t o = {.n = 0};
    put1(&o, seq >= 0 ? 0x87 : 0x86);
    put(&o, "\xa1v\x01\xa1k\xa6pose6d\xa1t", 14);
    put_uint(&o, (uint64_t)t);
    put(&o, "\xa1p\x93", 3);
    for (int k = 0; k < 3; k++) put_double(&o, p[k]);
    put(&o, "\xa1q\x94", 3);
    for (int k = 0; k < 4; k++) put_double(&o, qn[k]);
    put(&o, "\xa1" "c" "\xc0", 3);
    if (seq >= 0) {
        put(&o, "\xa1s", 2);
        put_uint(&o, (uint64_t)seq);
    }
    return PyBytes_FromStringAndSize((const char *)o.b, o.n);
}

static PyObject *configure(PyObject *self, PyObject *args) {
    if (!PyArg_ParseTuple(args, "ndd", &MAX_MESSAGE_BYTES, &QUAT_NORM_TOL, &PSD_TOL))
        return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"encode", (PyCFunction)(void (*)(void))encode, METH_FASTCALL,
     "encode(t, position, quaternion, seq) -> bytes or None (encode in Python)"},
    {"configure", configure, METH_VARARGS,
     "configure(max_message_bytes, quat_norm_tol, psd_tol): the codec's limits"},
    {"decode", decode, METH_O,
     "decode(data) -> (t, seq, position, quaternion, covariance) or None (decode in Python)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_pose", NULL, -1, methods};

PyMODINIT_FUNC PyInit__pose(void) { return uma_twin_module(&module); }
