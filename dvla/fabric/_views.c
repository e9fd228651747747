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
 * bytes are read-only and keep the bytes object alive. Every offset is bounds-checked.
 *
 * build(data, new, cls, spans, slots) goes one step further for a message class whose fields
 * need no checker beyond their wire type: it also reads every scalar slot and returns the
 * message itself, made by new(cls) (object.__new__) with its fields stored in its __dict__,
 * or None where the generated Python function would answer None (a differing span, a fixint
 * or bool byte outside its range, invalid UTF-8). The caller runs the message's value checks.
 *
 *   slots: tuple of (kind, field, dict key or None, offset, arg), kinds as in layout.py:
 *          0 positive fixint, 1 negative fixint, 2 bool, 3 scalar (arg: struct code, one of
 *          "BHIQbhiqfd", big-endian), 4 str (arg: length), 5 bin (arg: length),
 *          6 array (arg: (offset, dtype, shape), as for views), 7 nil
 *
 * The module is optional: without it (no C compiler at install time) layout.py uses Python.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>
#include <string.h>

#if PY_VERSION_HEX < 0x030B0000 /* public from 3.11 on */
#define PyFloat_Unpack4 _PyFloat_Unpack4
#define PyFloat_Unpack8 _PyFloat_Unpack8
#endif

/* The buffer of `data`, writable when it allows that (bytearray), else read-only (bytes). */
static int open_data(PyObject *data, Py_buffer *view, int *writable) {
    *writable = 1;
    if (PyObject_GetBuffer(data, view, PyBUF_WRITABLE) == 0) return 0;
    PyErr_Clear();
    *writable = 0;
    return PyObject_GetBuffer(data, view, PyBUF_SIMPLE);
}

/* The base object of views of `data` (new reference): the object itself when immutable, a
 * memoryview (an export that pins the buffer) when writable. */
static PyObject *view_base(PyObject *data, int writable) {
    return writable ? PyMemoryView_FromObject(data) : Py_NewRef(data);
}

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
    int writable;
    if (open_data(data, &view, &writable) < 0) return NULL;
    const char *buf = (const char *)view.buf;
    Py_ssize_t len = view.len;
    int match = spans_match(buf, len, spans);
    if (match <= 0) {
        PyBuffer_Release(&view);
        if (match < 0) return NULL;
        Py_RETURN_NONE;
    }
    PyObject *base = view_base(data, writable);
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

enum { K_FIXPOS, K_FIXNEG, K_BOOL, K_SCALAR, K_STR, K_BIN, K_ARRAY, K_NONE };

static unsigned long long read_be(const unsigned char *p, int width) {
    unsigned long long v = 0;
    for (int i = 0; i < width; i++) v = (v << 8) | p[i];
    return v;
}

/* One slot's value (new reference); NULL with no error set means "not this layout". */
static PyObject *read_slot(const char *buf, Py_ssize_t len, int writable, PyObject *base, long kind,
                           Py_ssize_t off, PyObject *arg) {
    const unsigned char *p = (const unsigned char *)buf + off;
    if (off < 0 || off >= len) {
        PyErr_SetString(PyExc_ValueError, "slots: offset beyond the end of the data");
        return NULL;
    }
    switch (kind) {
    case K_FIXPOS:
        if (p[0] > 0x7F) return NULL;
        return PyLong_FromLong(p[0]);
    case K_FIXNEG:
        if (p[0] < 0xE0) return NULL;
        return PyLong_FromLong((long)p[0] - 0x100);
    case K_BOOL:
        if (p[0] != 0xC2 && p[0] != 0xC3) return NULL;
        return PyBool_FromLong(p[0] == 0xC3);
    case K_SCALAR: {
        if (!PyUnicode_Check(arg) || PyUnicode_GET_LENGTH(arg) != 1) break;
        Py_UCS4 code = PyUnicode_READ_CHAR(arg, 0);
        int width = 0, is_signed = 0;
        switch (code) {
        case 'B': width = 1; break;
        case 'H': width = 2; break;
        case 'I': width = 4; break;
        case 'Q': width = 8; break;
        case 'b': width = 1; is_signed = 1; break;
        case 'h': width = 2; is_signed = 1; break;
        case 'i': width = 4; is_signed = 1; break;
        case 'q': width = 8; is_signed = 1; break;
        case 'f': width = 4; break;
        case 'd': width = 8; break;
        default: break;
        }
        if (width == 0 || width > len - off) break;
        if (code == 'f') return PyFloat_FromDouble(PyFloat_Unpack4((const char *)p, 0));
        if (code == 'd') return PyFloat_FromDouble(PyFloat_Unpack8((const char *)p, 0));
        unsigned long long u = read_be(p, width);
        if (!is_signed) return PyLong_FromUnsignedLongLong(u);
        int shift = 64 - 8 * width; /* sign-extend */
        return PyLong_FromLongLong(((long long)(u << shift)) >> shift);
    }
    case K_STR:
    case K_BIN: {
        Py_ssize_t n = PyLong_AsSsize_t(arg);
        if (n == -1 && PyErr_Occurred()) return NULL;
        if (n < 0 || n > len - off) break;
        if (kind == K_BIN) return PyBytes_FromStringAndSize((const char *)p, n);
        PyObject *str = PyUnicode_DecodeUTF8((const char *)p, n, NULL);
        if (str == NULL && PyErr_ExceptionMatches(PyExc_UnicodeDecodeError)) PyErr_Clear();
        return str;
    }
    case K_ARRAY: /* arg: (offset, dtype, shape), as for views() */
        return make_view(buf, len, writable, base, arg);
    case K_NONE:
        Py_RETURN_NONE;
    default:
        break;
    }
    PyErr_SetString(PyExc_ValueError, "slots: bad slot description");
    return NULL;
}

static PyObject *build(PyObject *self, PyObject *args) {
    PyObject *data, *new_fn, *cls, *spans, *slots;
    if (!PyArg_ParseTuple(args, "OOOO!O!:build", &data, &new_fn, &cls, &PyTuple_Type, &spans, &PyTuple_Type, &slots))
        return NULL;
    Py_buffer view;
    int writable;
    if (open_data(data, &view, &writable) < 0) return NULL;
    const char *buf = (const char *)view.buf;
    Py_ssize_t len = view.len;
    PyObject *base = NULL, *fields = NULL, *msg = NULL, *dict = NULL, *result = NULL;
    int match = spans_match(buf, len, spans);
    if (match < 0) goto done;
    if (match == 0) {
        result = Py_NewRef(Py_None);
        goto done;
    }
    base = view_base(data, writable);
    fields = PyDict_New();
    if (base == NULL || fields == NULL) goto done;
    Py_ssize_t n = PyTuple_GET_SIZE(slots);
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *slot = PyTuple_GET_ITEM(slots, i);
        if (!PyTuple_Check(slot) || PyTuple_GET_SIZE(slot) != 5 || !PyUnicode_Check(PyTuple_GET_ITEM(slot, 1))) {
            PyErr_SetString(PyExc_TypeError, "slots: expected (kind, field, key, offset, arg) tuples");
            goto done;
        }
        long kind = PyLong_AsLong(PyTuple_GET_ITEM(slot, 0));
        Py_ssize_t off = PyLong_AsSsize_t(PyTuple_GET_ITEM(slot, 3));
        if ((kind == -1 || off == -1) && PyErr_Occurred()) goto done;
        PyObject *value = read_slot(buf, len, writable, base, kind, off, PyTuple_GET_ITEM(slot, 4));
        if (value == NULL) {
            if (!PyErr_Occurred()) result = Py_NewRef(Py_None); /* not this layout */
            goto done;
        }
        PyObject *field = PyTuple_GET_ITEM(slot, 1), *key = PyTuple_GET_ITEM(slot, 2);
        int rc;
        if (key == Py_None) {
            rc = PyDict_SetItem(fields, field, value);
        } else {
            PyObject *sub = PyDict_GetItemWithError(fields, field); /* borrowed */
            if (sub == NULL && !PyErr_Occurred()) {
                sub = PyDict_New();
                if (sub != NULL) {
                    rc = PyDict_SetItem(fields, field, sub);
                    Py_DECREF(sub); /* fields holds it */
                    if (rc < 0) sub = NULL;
                }
            }
            rc = sub == NULL ? -1 : PyDict_SetItem(sub, key, value);
        }
        Py_DECREF(value);
        if (rc < 0) goto done;
    }
    msg = PyObject_CallOneArg(new_fn, cls);
    if (msg == NULL) goto done;
    dict = PyObject_GenericGetDict(msg, NULL);
    if (dict == NULL || PyDict_Update(dict, fields) < 0) goto done;
    result = Py_NewRef(msg);
done:
    Py_XDECREF(dict);
    Py_XDECREF(msg);
    Py_XDECREF(fields);
    Py_XDECREF(base);
    PyBuffer_Release(&view);
    return result;
}

static PyMethodDef methods[] = {
    {"build", build, METH_VARARGS,
     "build(data, new, cls, spans, slots) -> the message, or None when data does not have this layout"},
    {"views", views, METH_VARARGS,
     "views(data, spans, arrays) -> tuple of array views, or None when a constant span differs"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_views", NULL, -1, methods};

PyMODINIT_FUNC PyInit__views(void) {
    import_array();
    return PyModule_Create(&module);
}
