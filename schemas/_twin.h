/* What every compiled twin's module init shares: the module carries SOURCE_HASH, the SHA-256
   of its C source and this header that setup.py defines as UMA_SOURCE_HASH;
   schemas/native.py uses a twin only where that hash is the one of the sources beside it,
   so a build older than its source is never run. */
#ifndef UMA_TWIN_H
#define UMA_TWIN_H

#include <Python.h>

#ifndef UMA_SOURCE_HASH
#define UMA_SOURCE_HASH ""
#endif

static PyObject *uma_twin_module(struct PyModuleDef *definition) {
    PyObject *m = PyModule_Create(definition);
    if (m != NULL && PyModule_AddStringConstant(m, "SOURCE_HASH", UMA_SOURCE_HASH) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}

#endif
