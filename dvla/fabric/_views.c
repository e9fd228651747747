/* dvla.fabric._views: the per-message part of the layout decoder's fast path, in C.
 *
 * views(data, spans, arrays) checks that every constant span of a learned layout is byte for
 * byte present in `data` and returns a tuple of zero-copy numpy views of its array slots, or
 * None when a span differs (the caller then runs the full decoder). It does what the generated
 * Python build function of dvla/fabric/layout.py does for spans and arrays, without a Python
 * slice per span and an ndarray constructor call per array.
 *
 *   spans:  tuple of (offset: int, constant: bytes)
 *   arrays: tuple of (offset: int, dtype: numpy.dtype, shape: tuple of int)
 *
 * Views of a writable buffer (bytearray) are writable and keep a memoryview of it as their
 * base, so the buffer cannot be resized while one lives (as numpy.frombuffer does); views of
 * bytes are read-only and keep the bytes object alive. Every offset is bounds-checked. The
 * module is optional: without it (no C compiler at install time) layout.py uses Python.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <string.h>

static int spans_match(const char *buf, Py_ssize_t len, PyObject *spans) {
    Py_ssize_t ns = PyTuple_GET_SIZE(spans);
    for (Py_ssize_t i = 0; i < ns; i++) {
        PyObject *item = PyTuple_GET_ITEM(spans, i);
        if (!PyTuple_Check(item) || PyTuple_GET_SIZE(item) != 2 || !PyBytes_Check(PyTuple_GET_ITEM(item, 1))) {
            PyErr_SetString(PyExc_TypeError, "spans: expected (int, bytes) tuples");
            return -1;
        }
        Py_ssize_t off = PyLong_AsSsize_t(PyTuple_GET_ITEM(item, 0));
        if (off == -1 && PyErr_Occurred()) return -1;
        PyObject *c = PyTuple_GET_ITEM(item, 1);
        Py_ssize_t n = PyBytes_GET_SIZE(c);
        if (off < 0 || n > len - off || memcmp(buf + off, PyBytes_AS_STRING(c), (size_t)n) != 0) return 0;
    }
    return 1;
}

static PyObject *make_view(const char *buf, Py_ssize_t len, int writable, PyObject *base, PyObject *item) {
    if (!PyTuple_Check(item) || PyTuple_GET_SIZE(item) != 3 || !PyArray_DescrCheck(PyTuple_GET_ITEM(item, 1))
        || !PyTuple_Check(PyTuple_GET_ITEM(item, 2))) {
        PyErr_SetString(PyExc_TypeError, "arrays: expected (int, numpy.dtype, tuple) tuples");
        return NULL;
    }
    Py_ssize_t off = PyLong_AsSsize_t(PyTuple_GET_ITEM(item, 0));
    if (off == -1 && PyErr_Occurred()) return NULL;
    PyArray_Descr *descr = (PyArray_Descr *)PyTuple_GET_ITEM(item, 1);
    PyObject *shape = PyTuple_GET_ITEM(item, 2);
    Py_ssize_t nd = PyTuple_GET_SIZE(shape);
    if (nd > NPY_MAXDIMS) {
        PyErr_SetString(PyExc_ValueError, "arrays: too many dimensions");
        return NULL;
    }
    npy_intp dims[NPY_MAXDIMS];
    Py_ssize_t total = (Py_ssize_t)PyDataType_ELSIZE(descr);
    for (Py_ssize_t d = 0; d < nd; d++) {
        Py_ssize_t dim = PyLong_AsSsize_t(PyTuple_GET_ITEM(shape, d));
        if (dim == -1 && PyErr_Occurred()) return NULL;
        if (dim < 0 || (dim > 0 && total > PY_SSIZE_T_MAX / dim)) {
            PyErr_SetString(PyExc_ValueError, "arrays: bad dimension");
            return NULL;
        }
        dims[d] = (npy_intp)dim;
        total *= dim;
    }
    if (off < 0 || total > len - off) {
        PyErr_SetString(PyExc_ValueError, "arrays: view beyond the end of the data");
        return NULL;
    }
    Py_INCREF(descr); /* PyArray_NewFromDescr steals it */
    PyObject *arr = PyArray_NewFromDescr(&PyArray_Type, descr, (int)nd, dims, NULL, (void *)(buf + off),
                                         writable ? NPY_ARRAY_CARRAY : NPY_ARRAY_CARRAY_RO, NULL);
    if (arr == NULL) return NULL;
    Py_INCREF(base); /* PyArray_SetBaseObject steals it, also on failure */
    if (PyArray_SetBaseObject((PyArrayObject *)arr, base) < 0) {
        Py_DECREF(arr);
        return NULL;
    }
    return arr;
}

static PyObject *views(PyObject *self, PyObject *args) {
    PyObject *data, *spans, *arrays;
    if (!PyArg_ParseTuple(args, "OO!O!:views", &data, &PyTuple_Type, &spans, &PyTuple_Type, &arrays)) return NULL;
    Py_buffer view;
    int writable = 1;
    if (PyObject_GetBuffer(data, &view, PyBUF_WRITABLE) < 0) {
        PyErr_Clear();
        writable = 0;
        if (PyObject_GetBuffer(data, &view, PyBUF_SIMPLE) < 0) return NULL;
    }
    const char *buf = (const char *)view.buf;
    Py_ssize_t len = view.len;
    int match = spans_match(buf, len, spans);
    if (match <= 0) {
        PyBuffer_Release(&view);
        if (match < 0) return NULL;
        Py_RETURN_NONE;
    }
    /* The views' base: the object itself when immutable, a memoryview (an export that pins the
     * buffer) when writable. */
    PyObject *base;
    if (writable) {
        base = PyMemoryView_FromObject(data);
    } else {
        Py_INCREF(data);
        base = data;
    }
    PyBuffer_Release(&view);
    if (base == NULL) return NULL;
    Py_ssize_t na = PyTuple_GET_SIZE(arrays);
    PyObject *out = PyTuple_New(na);
    if (out == NULL) {
        Py_DECREF(base);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < na; i++) {
        PyObject *arr = make_view(buf, len, writable, base, PyTuple_GET_ITEM(arrays, i));
        if (arr == NULL) {
            Py_DECREF(out);
            Py_DECREF(base);
            return NULL;
        }
        PyTuple_SET_ITEM(out, i, arr);
    }
    Py_DECREF(base);
    return out;
}

static PyMethodDef methods[] = {
    {"views", views, METH_VARARGS,
     "views(data, spans, arrays) -> tuple of array views, or None when a constant span differs"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_views", NULL, -1, methods};

PyMODINIT_FUNC PyInit__views(void) {
    import_array();
    return PyModule_Create(&module);
}
