/*
 * rtu_crc_py.c -- pyrtu.core._crcfast: the CRC-16/MODBUS of csrc/rtu_crc.c as
 * CPython builtins.
 *
 * Spec: "Modbus over Serial Line V1.02", 6.2.2 (CRC checking: polynomial
 * 0xA001 reflected, register preset to 0xFFFF, the CRC appended low byte
 * first) and Appendix B (CRC generation).  The CRC itself is rtu_crc16() of
 * csrc/rtu_crc.c with its run-time dispatch (slicing-by-8, PCLMULQDQ,
 * VPCLMULQDQ); nothing here computes a CRC.
 *
 * Why a second extension beside the cffi core: a cffi call costs some
 * 200 ns, a builtin called with METH_FASTCALL about 30 ns, and the CRC of an
 * 8-byte frame about 3 ns.  The functions take what the pure-Python twin
 * (pyrtu/core/_pure/crc.py) takes and raise what it raises, with the same
 * messages: any buffer (bytes without a buffer request; a strided one is
 * read in logical order from a copy, as memoryview.tobytes() gives it), a
 * TypeError naming the argument for anything else, and for crc16 a seed
 * 0..0xFFFF (TypeError for a non-integer or a bool, ValueError out of range).
 *
 * This file uses the CPython API, so it lives below csrc/, not in it: the
 * fuzz harnesses (the Makefile compiles the .c files of csrc/ itself) and
 * the cffi build (pyrtu/core/_build_core.py, the same files) do not take it.
 * setup.py builds it with csrc/rtu_crc.c as the module pyrtu.core._crcfast.
 *
 * The stable ABI: setup.py defines Py_LIMITED_API 0x030A0000 (CPython 3.10)
 * where the interpreter allows it, and the wheel is one cp310-abi3 for every
 * CPython from 3.10; the file uses nothing outside that API.  The buffer
 * protocol (PyObject_GetBuffer, Py_buffer) joined the limited API only in
 * 3.11, so under the 3.10 one a bytes object is read in place, a bytearray in
 * place below RTU_PY_NOGIL_MIN (the GIL held: nothing can resize it), and any
 * other buffer (memoryview, array, a bytearray from RTU_PY_NOGIL_MIN) through
 * one copy of its bytes in logical order (bytes(memoryview(obj))).  Built
 * against the full API (a free-threaded or a debug interpreter, where there is
 * no abi3) or a limited API from 3.11, the buffer protocol reads every buffer
 * in place.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#if !defined(Py_LIMITED_API) || Py_LIMITED_API + 0 >= 0x030B0000
#define RTU_PY_BUFFER_API 1
#else
#define RTU_PY_BUFFER_API 0
#endif

#include <stdint.h>
#include <string.h>

#include "rtu_crc.h"

/* Above this many bytes the CRC runs without the GIL (some 1 us of work at
 * the slicing speed, far more than the cost of releasing it). */
#define RTU_PY_NOGIL_MIN 65536

/* ------------------------------------------------------------------------ */
/* arguments                                                                 */
/* ------------------------------------------------------------------------ */

/* Raise `exc` with "<prefix>, not <type(obj).__name__>", as the twin's messages
 * print it (the type's __name__: its tp_name is not in the limited API). */
static void rtu_py_type_error(PyObject *exc, const char *prefix, PyObject *obj)
{
    PyObject *name = PyObject_GetAttrString((PyObject *)Py_TYPE(obj), "__name__");

    if (name == NULL || !PyUnicode_Check(name)) {
        Py_XDECREF(name);
        PyErr_Clear();
        PyErr_Format(exc, "%s, not an object of unknown type", prefix);
        return;
    }
    PyErr_Format(exc, "%s, not %.200U", prefix, name);
    Py_DECREF(name);
}

/* Bind positional and keyword arguments to `nmax` parameters named `kw`
 * (the first `nmin` required), as a Python function with these parameters
 * would, with its messages.  out[i] is a borrowed reference or NULL. */
static int rtu_py_args(const char *fname, const char *const *kw, Py_ssize_t nmin, Py_ssize_t nmax,
                       PyObject *const *args, Py_ssize_t nargs, PyObject *kwnames, PyObject **out)
{
    Py_ssize_t i, j, nkw;

    if (nargs > nmax) {
        if (nmin == nmax)
            PyErr_Format(PyExc_TypeError, "%s() takes %zd positional argument%s but %zd %s given",
                         fname, nmax, nmax == 1 ? "" : "s", nargs, nargs == 1 ? "was" : "were");
        else
            PyErr_Format(PyExc_TypeError,
                         "%s() takes from %zd to %zd positional arguments but %zd %s given", fname,
                         nmin, nmax, nargs, nargs == 1 ? "was" : "were");
        return -1;
    }
    for (i = 0; i < nmax; i++)
        out[i] = i < nargs ? args[i] : NULL;
    nkw = kwnames ? PyTuple_Size(kwnames) : 0;
    for (j = 0; j < nkw; j++) {
        PyObject *key = PyTuple_GetItem(kwnames, j);
        if (key == NULL)
            return -1;
        for (i = 0; i < nmax; i++)
            if (PyUnicode_CompareWithASCIIString(key, kw[i]) == 0)
                break;
        if (i == nmax) {
            PyErr_Format(PyExc_TypeError, "%s() got an unexpected keyword argument '%U'", fname,
                         key);
            return -1;
        }
        if (out[i] != NULL) {
            PyErr_Format(PyExc_TypeError, "%s() got multiple values for argument '%s'", fname,
                         kw[i]);
            return -1;
        }
        out[i] = args[nargs + j];
    }
    for (i = 0; i < nmin; i++)
        if (out[i] == NULL) {
            PyErr_Format(PyExc_TypeError, "%s() missing 1 required positional argument: '%s'",
                         fname, kw[i]);
            return -1;
        }
    return 0;
}

/* The bytes of a buffer argument, in logical order (as memoryview.tobytes()
 * gives them): straight from a bytes object; else (the full or the 3.11
 * limited API) from a buffer request, a strided one through a C-order copy;
 * else (the 3.10 limited API: no buffer protocol) a bytearray in place or a
 * copy made by bytes(memoryview(obj)).  `stable`: nothing can change or free
 * the bytes while the GIL is released (a bytes object, a held buffer, a copy). */
typedef struct {
    const uint8_t *p;
    Py_ssize_t n;
    int stable;
#if RTU_PY_BUFFER_API
    Py_buffer view;
    int held;   /* view to release */
    void *copy; /* PyMem block to free */
#else
    PyObject *owner; /* the copy (a bytes object) to release */
#endif
} rtu_py_data;

static void rtu_py_not_bytes_like(PyObject *obj, const char *name)
{
    char prefix[64];

    PyOS_snprintf(prefix, sizeof prefix, "%s must be a bytes-like object", name);
    rtu_py_type_error(PyExc_TypeError, prefix, obj);
}

static int rtu_py_bytes(PyObject *obj, rtu_py_data *d)
{
    char *p;

    if (PyBytes_AsStringAndSize(obj, &p, &d->n) < 0)
        return -1;
    d->p = (const uint8_t *)p;
    d->stable = 1;
    return 0;
}

#if RTU_PY_BUFFER_API
static int rtu_py_data_get(PyObject *obj, const char *name, rtu_py_data *d)
{
    d->held = 0;
    d->copy = NULL;
    if (PyBytes_Check(obj)) /* a subclass too: its bytes cannot change */
        return rtu_py_bytes(obj, d);
    d->stable = 1; /* a held buffer cannot be resized or freed */
    if (PyObject_GetBuffer(obj, &d->view, PyBUF_SIMPLE) == 0) {
        d->held = 1;
        d->p = (const uint8_t *)d->view.buf;
        d->n = d->view.len;
        return 0;
    }
    if (PyErr_ExceptionMatches(PyExc_BufferError) && PyObject_CheckBuffer(obj)) {
        /* not C-contiguous: its bytes in logical order, as the twin reads it */
        PyErr_Clear();
        if (PyObject_GetBuffer(obj, &d->view, PyBUF_FULL_RO) < 0)
            return -1;
        d->held = 1;
        d->copy = PyMem_Malloc(d->view.len > 0 ? (size_t)d->view.len : 1);
        if (d->copy == NULL) {
            PyBuffer_Release(&d->view);
            d->held = 0;
            PyErr_NoMemory();
            return -1;
        }
        if (PyBuffer_ToContiguous(d->copy, &d->view, d->view.len, 'C') < 0) {
            PyMem_Free(d->copy);
            d->copy = NULL;
            PyBuffer_Release(&d->view);
            d->held = 0;
            return -1;
        }
        d->p = (const uint8_t *)d->copy;
        d->n = d->view.len;
        return 0;
    }
    if (PyErr_ExceptionMatches(PyExc_TypeError)) {
        PyErr_Clear();
        rtu_py_not_bytes_like(obj, name);
    }
    return -1;
}

static void rtu_py_data_release(rtu_py_data *d)
{
    if (d->copy != NULL) {
        PyMem_Free(d->copy);
        d->copy = NULL;
    }
    if (d->held) {
        PyBuffer_Release(&d->view);
        d->held = 0;
    }
}
#else
static int rtu_py_data_get(PyObject *obj, const char *name, rtu_py_data *d)
{
    PyObject *view;

    d->owner = NULL;
    if (PyBytes_Check(obj)) /* a subclass too: its bytes cannot change */
        return rtu_py_bytes(obj, d);
    if (PyByteArray_CheckExact(obj) && PyByteArray_Size(obj) < RTU_PY_NOGIL_MIN) {
        /* read with the GIL held (rtu_py_crc), so no thread can resize it meanwhile */
        d->p = (const uint8_t *)PyByteArray_AsString(obj);
        d->n = PyByteArray_Size(obj);
        d->stable = 0;
        return 0;
    }
    view = PyMemoryView_FromObject(obj); /* TypeError: not a buffer */
    if (view == NULL) {
        if (PyErr_ExceptionMatches(PyExc_TypeError)) {
            PyErr_Clear();
            rtu_py_not_bytes_like(obj, name);
        }
        return -1;
    }
    d->owner = PyBytes_FromObject(view); /* its bytes in logical order */
    Py_DECREF(view);
    if (d->owner == NULL)
        return -1;
    if (rtu_py_bytes(d->owner, d) < 0) {
        Py_CLEAR(d->owner);
        return -1;
    }
    return 0;
}

static void rtu_py_data_release(rtu_py_data *d) { Py_CLEAR(d->owner); }
#endif

/* The register's initial value: an int (not a bool) 0..0xFFFF (6.2.2 presets
 * it to 0xFFFF; another value continues an earlier CRC). */
static int rtu_py_seed(PyObject *obj, uint16_t *out)
{
    int overflow = 0;
    long v;

    if (!PyLong_Check(obj) || PyBool_Check(obj)) {
        rtu_py_type_error(PyExc_TypeError, "crc must be an integer 0..0xFFFF", obj);
        return -1;
    }
    v = PyLong_AsLongAndOverflow(obj, &overflow);
    if (v == -1 && PyErr_Occurred())
        return -1;
    if (overflow || v < 0 || v > 0xFFFF) {
        PyErr_Format(PyExc_ValueError, "crc must be an integer 0..0xFFFF, not %R", obj);
        return -1;
    }
    *out = (uint16_t)v;
    return 0;
}

static uint16_t rtu_py_crc(const rtu_py_data *d, Py_ssize_t n, uint16_t crc)
{
    uint16_t out;

    if (n < RTU_PY_NOGIL_MIN || !d->stable)
        return rtu_crc16(d->p, (size_t)n, crc);
    Py_BEGIN_ALLOW_THREADS out = rtu_crc16(d->p, (size_t)n, crc);
    Py_END_ALLOW_THREADS return out;
}

/* ------------------------------------------------------------------------ */
/* functions                                                                 */
/* ------------------------------------------------------------------------ */

static const char *const rtu_py_kw_data_crc[] = {"data", "crc"};
static const char *const rtu_py_kw_data[] = {"data"};
static const char *const rtu_py_kw_adu[] = {"adu"};

PyDoc_STRVAR(rtu_py_crc16_doc,
             "crc16(data, crc=0xFFFF)\n--\n\n"
             "CRC-16/MODBUS of ``data``, continuing from ``crc`` (0xFFFF to start).");

static PyObject *rtu_py_crc16(PyObject *self, PyObject *const *args, Py_ssize_t nargs,
                              PyObject *kwnames)
{
    PyObject *a[2];
    rtu_py_data d;
    uint16_t crc = RTU_CRC_INIT;

    (void)self;
    if (kwnames == NULL && nargs == 1) {
        a[0] = args[0];
        a[1] = NULL;
    } else if (rtu_py_args("crc16", rtu_py_kw_data_crc, 1, 2, args, nargs, kwnames, a) < 0) {
        return NULL;
    }
    if (rtu_py_data_get(a[0], "data", &d) < 0)
        return NULL;
    if (a[1] != NULL && rtu_py_seed(a[1], &crc) < 0) {
        rtu_py_data_release(&d);
        return NULL;
    }
    crc = rtu_py_crc(&d, d.n, crc);
    rtu_py_data_release(&d);
    return PyLong_FromLong((long)crc);
}

PyDoc_STRVAR(rtu_py_crc16_bytes_doc, "crc16_bytes(data)\n--\n\n"
                                     "The CRC of ``data`` as its two wire bytes, low byte first.");

static PyObject *rtu_py_crc16_bytes(PyObject *self, PyObject *const *args, Py_ssize_t nargs,
                                    PyObject *kwnames)
{
    PyObject *a[1];
    rtu_py_data d;
    uint16_t crc;
    char wire[2];

    (void)self;
    if (kwnames == NULL && nargs == 1)
        a[0] = args[0];
    else if (rtu_py_args("crc16_bytes", rtu_py_kw_data, 1, 1, args, nargs, kwnames, a) < 0)
        return NULL;
    if (rtu_py_data_get(a[0], "data", &d) < 0)
        return NULL;
    crc = rtu_py_crc(&d, d.n, RTU_CRC_INIT);
    rtu_py_data_release(&d);
    wire[0] = (char)(crc & 0xFF); /* 6.2.2: the low-order byte goes first */
    wire[1] = (char)(crc >> 8);
    return PyBytes_FromStringAndSize(wire, 2);
}

PyDoc_STRVAR(rtu_py_crc16_swapped_doc,
             "crc16_swapped(data)\n--\n\n"
             "The CRC of ``data`` byte-swapped: ``crc16_swapped(d).to_bytes(2, \"big\")`` is\n"
             "``crc16_bytes(d)``.");

static PyObject *rtu_py_crc16_swapped(PyObject *self, PyObject *const *args, Py_ssize_t nargs,
                                      PyObject *kwnames)
{
    PyObject *a[1];
    rtu_py_data d;
    uint16_t crc;

    (void)self;
    if (kwnames == NULL && nargs == 1)
        a[0] = args[0];
    else if (rtu_py_args("crc16_swapped", rtu_py_kw_data, 1, 1, args, nargs, kwnames, a) < 0)
        return NULL;
    if (rtu_py_data_get(a[0], "data", &d) < 0)
        return NULL;
    crc = rtu_py_crc(&d, d.n, RTU_CRC_INIT);
    rtu_py_data_release(&d);
    return PyLong_FromLong((long)(((crc & 0xFFu) << 8) | (crc >> 8)));
}

PyDoc_STRVAR(rtu_py_check_crc_doc,
             "check_crc(adu)\n--\n\n"
             "True when the last two bytes of ``adu`` are the CRC of the rest.");

static PyObject *rtu_py_check_crc(PyObject *self, PyObject *const *args, Py_ssize_t nargs,
                                  PyObject *kwnames)
{
    PyObject *a[1];
    rtu_py_data d;
    uint16_t crc;
    int ok = 0;

    (void)self;
    if (kwnames == NULL && nargs == 1)
        a[0] = args[0];
    else if (rtu_py_args("check_crc", rtu_py_kw_adu, 1, 1, args, nargs, kwnames, a) < 0)
        return NULL;
    if (rtu_py_data_get(a[0], "adu", &d) < 0)
        return NULL;
    if (d.n >= 3) { /* address, function code, and the two CRC bytes (6.2.2) */
        crc = rtu_py_crc(&d, d.n - 2, RTU_CRC_INIT);
        ok = d.p[d.n - 2] == (crc & 0xFF) && d.p[d.n - 1] == (crc >> 8);
    }
    rtu_py_data_release(&d);
    return PyBool_FromLong(ok);
}

PyDoc_STRVAR(rtu_py_add_crc_doc, "add_crc(data)\n--\n\n"
                                 "``data`` with its CRC appended, low byte first (CFW100 4.2.4).");

static PyObject *rtu_py_add_crc(PyObject *self, PyObject *const *args, Py_ssize_t nargs,
                                PyObject *kwnames)
{
    PyObject *a[1];
    PyObject *out;
    rtu_py_data d;
    uint16_t crc;
    char *q;

    (void)self;
    if (kwnames == NULL && nargs == 1)
        a[0] = args[0];
    else if (rtu_py_args("add_crc", rtu_py_kw_data, 1, 1, args, nargs, kwnames, a) < 0)
        return NULL;
    if (rtu_py_data_get(a[0], "data", &d) < 0)
        return NULL;
    if (d.n > PY_SSIZE_T_MAX - 2) {
        rtu_py_data_release(&d);
        return PyErr_NoMemory();
    }
    out = PyBytes_FromStringAndSize(NULL, d.n + 2);
    if (out == NULL) {
        rtu_py_data_release(&d);
        return NULL;
    }
    q = PyBytes_AsString(out);
    if (q == NULL) {
        Py_DECREF(out);
        rtu_py_data_release(&d);
        return NULL;
    }
    if (d.n > 0)
        memcpy(q, d.p, (size_t)d.n);
    crc = rtu_py_crc(&d, d.n, RTU_CRC_INIT);
    rtu_py_data_release(&d);
    q[d.n] = (char)(crc & 0xFF); /* 6.2.2: low-order byte first */
    q[d.n + 1] = (char)(crc >> 8);
    return out;
}

/* ------------------------------------------------------------------------ */
/* module                                                                    */
/* ------------------------------------------------------------------------ */

#define RTU_PY_FN(name, fn, doc)                                                    \
    {                                                                               \
        name, (PyCFunction)(void (*)(void))(fn), METH_FASTCALL | METH_KEYWORDS, doc \
    }

static PyMethodDef rtu_py_methods[] = {
    RTU_PY_FN("crc16", rtu_py_crc16, rtu_py_crc16_doc),
    RTU_PY_FN("crc16_bytes", rtu_py_crc16_bytes, rtu_py_crc16_bytes_doc),
    RTU_PY_FN("crc16_swapped", rtu_py_crc16_swapped, rtu_py_crc16_swapped_doc),
    RTU_PY_FN("check_crc", rtu_py_check_crc, rtu_py_check_crc_doc),
    RTU_PY_FN("add_crc", rtu_py_add_crc, rtu_py_add_crc_doc),
    {NULL, NULL, 0, NULL},
};

PyDoc_STRVAR(rtu_py_module_doc,
             "CRC-16/MODBUS (Modbus over Serial Line V1.02, 6.2.2) of pyrtu's C core as\n"
             "builtins: the C backend's crc16, add_crc and check_crc, and the call shapes\n"
             "of pyrtu.core.crcshapes.");

static struct PyModuleDef rtu_py_module = {
    PyModuleDef_HEAD_INIT,
    "pyrtu.core._crcfast",
    rtu_py_module_doc,
    0,
    rtu_py_methods,
    NULL,
    NULL,
    NULL,
    NULL,
};

PyMODINIT_FUNC PyInit__crcfast(void);

PyMODINIT_FUNC PyInit__crcfast(void) { return PyModuleDef_Init(&rtu_py_module); }
