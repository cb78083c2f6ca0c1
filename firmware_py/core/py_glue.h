/*
 * The CPython glue's shared helpers (_coremodule.c and every core/py_<area>.c): binding a caller's
 * array as a buffer at construction, and reading a METH_FASTCALL call's numbers. Static inline:
 * each glue file that includes this header has its own copy, no symbol is shared between them.
 * Outside the firmware core (src/ and include/ never include Python.h).
 */
#ifndef CT_PY_GLUE_H
#define CT_PY_GLUE_H

#ifndef PY_SSIZE_T_CLEAN
#define PY_SSIZE_T_CLEAN
#endif
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* the struct-module character of a buffer's items, its byte-order prefix ('@', '=', '<': native
 * on the little-endian hosts the extension builds for) skipped; "B" where the exporter gives none
 * (PEP 3118: unsigned bytes) */
/* Ready type t and add it to module m as `name`: 0, or -1 with the exception set (nothing held). */
static inline int ct_py_add_type(PyObject *m, PyTypeObject *t, const char *name)
{
    if (PyType_Ready(t) < 0)
        return -1;
    Py_INCREF(t);
    if (PyModule_AddObject(m, name, (PyObject *)t) < 0) {
        Py_DECREF(t);
        return -1;
    }
    return 0;
}

static inline const char *ct_py_format(const Py_buffer *v)
{
    const char *f = v->format;
    if (f == NULL)
        return "B";
    if (f[0] == '@' || f[0] == '=' || f[0] == '<')
        f++;
    return f;
}

/* Bind obj as a C-contiguous buffer (writable when asked) of at least n items of itemsize bytes
 * whose format is one character of `formats` ("d": float64, "ql": int64, "B": bytes, ...):
 * 0, or -1 with a TypeError naming `what` (nothing held then). */
static inline int ct_py_buffer(PyObject *obj, Py_ssize_t n, Py_ssize_t itemsize, const char *formats, int writable,
                               Py_buffer *view, const char *what)
{
    const char *f;
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: needs a %sC-contiguous buffer", what, writable ? "writable " : "");
        return -1;
    }
    f = ct_py_format(view);
    if (view->itemsize != itemsize || f[0] == '\0' || f[1] != '\0' || strchr(formats, f[0]) == NULL ||
        view->len < n * itemsize) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s: needs at least %zd items of %zd bytes (format %s)", what, n, itemsize,
                     formats);
        return -1;
    }
    return 0;
}

/* Bind the sequence `bufs` of exactly `count` float64 arrays, item i as ct_py_buffer does with at
 * least len[i] items, writable unless ro[i], named names[i]; its data pointer into ptr[i]: 0, or -1
 * with the error set (a ValueError naming `what` for a sequence of another length) and nothing held. */
static inline int ct_py_float_buffers(PyObject *bufs, int count, const Py_ssize_t *len, const int *ro,
                                      const char *const *names, Py_buffer *views, double **ptr, const char *what)
{
    PyObject *seq = PySequence_Check(bufs) ? PySequence_Fast(bufs, "") : NULL;
    int i;
    if (seq == NULL) {
        if (!PyErr_Occurred() || PyErr_ExceptionMatches(PyExc_TypeError)) {
            PyErr_Clear();
            PyErr_Format(PyExc_TypeError, "%s: buffers must be a sequence", what);
        }
        return -1;
    }
    if (PySequence_Fast_GET_SIZE(seq) != count) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "%s: needs %d buffers", what, count);
        return -1;
    }
    for (i = 0; i < count; ++i) {
        if (ct_py_buffer(PySequence_Fast_GET_ITEM(seq, i), len[i], 8, "d", !ro[i], &views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&views[i]);
            Py_DECREF(seq);
            return -1;
        }
        ptr[i] = (double *)views[i].buf;
    }
    Py_DECREF(seq);
    return 0;
}

/* The lengths of `count` buffers given per n (per_n[i] > 0: per_n[i] * n items; otherwise the fixed
 * count -per_n[i]) into len. */
static inline void ct_py_lengths_per_n(const int *per_n, int count, int n, Py_ssize_t *len)
{
    int i;
    for (i = 0; i < count; ++i)
        len[i] = per_n[i] > 0 ? (Py_ssize_t)per_n[i] * n : -(Py_ssize_t)per_n[i];
}

/* Take obj, when it is a float64 array of shape (rows, cols) (cols 0: 1-D of rows items) with any
 * strides in whole items, as a read-only view: 1 (v held, the caller releases it), or 0 with no error
 * set and nothing held (another kind of input: the caller's Python reference takes it) */
static inline int ct_py_view(PyObject *obj, Py_buffer *v, Py_ssize_t rows, Py_ssize_t cols)
{
    const char *f;
    if (PyObject_GetBuffer(obj, v, PyBUF_RECORDS_RO) < 0) {
        PyErr_Clear();
        return 0;
    }
    f = v->format;
    if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<'))
        f++;
    if (f == NULL || f[0] != 'd' || f[1] != '\0' || v->itemsize != 8 || v->strides == NULL ||
        (cols == 0 ? (v->ndim != 1 || v->shape[0] != rows)
                   : (v->ndim != 2 || v->shape[0] != rows || v->shape[1] != cols)) ||
        v->strides[0] % 8 != 0 || (cols > 0 && v->strides[1] % 8 != 0)) {
        PyBuffer_Release(v);
        return 0;
    }
    return 1;
}

/* a call's float argument (an int too) */
static inline int ct_py_double(PyObject *o, double *x)
{
    *x = PyFloat_AsDouble(o);
    return (*x == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

/* a call's integer argument */
static inline int ct_py_int64(PyObject *o, int64_t *x)
{
    long long v = PyLong_AsLongLong(o);
    if (v == -1 && PyErr_Occurred())
        return -1;
    *x = (int64_t)v;
    return 0;
}

/* an argument that must be a Python int into *x: 1, or 0 (the error cleared) when it is no int or
 * out of int64's range (the caller then hands the call back to its Python reference) */
static inline int ct_py_int_only(PyObject *o, int64_t *x)
{
    int overflow = 0;
    long long v;
    if (!PyLong_Check(o))
        return 0;
    v = PyLong_AsLongLongAndOverflow(o, &overflow);
    if ((v == -1 && PyErr_Occurred()) || overflow) {
        PyErr_Clear();
        return 0;
    }
    *x = (int64_t)v;
    return 1;
}

/* a signed 64-bit field's argument ('q') into *x: 1, or 0 (the error cleared) for anything
 * struct.pack would refuse */
static inline int ct_py_pack_q(PyObject *o, int64_t *x)
{
    int overflow = 0;
    long long v;
    PyObject *i = PyLong_Check(o) ? (Py_INCREF(o), o) : PyNumber_Index(o);
    if (i == NULL) {
        PyErr_Clear();
        return 0;
    }
    v = PyLong_AsLongLongAndOverflow(i, &overflow);
    Py_DECREF(i);
    if ((v == -1 && PyErr_Occurred()) || overflow) {
        PyErr_Clear();
        return 0;
    }
    *x = (int64_t)v;
    return 1;
}

/* an unsigned 64-bit field's argument ('Q') into *x: 1, or 0 (the error cleared) for anything
 * struct.pack would refuse */
static inline int ct_py_pack_Q(PyObject *o, uint64_t *x)
{
    unsigned long long v;
    PyObject *i = PyLong_Check(o) ? (Py_INCREF(o), o) : PyNumber_Index(o);
    if (i == NULL) {
        PyErr_Clear();
        return 0;
    }
    v = PyLong_AsUnsignedLongLong(i);
    Py_DECREF(i);
    if (v == (unsigned long long)-1 && PyErr_Occurred()) {
        PyErr_Clear();
        return 0;
    }
    *x = (uint64_t)v;
    return 1;
}

/* a METH_FASTCALL method's argument count */
static inline int ct_py_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", name, want, nargs);
        return -1;
    }
    return 0;
}

/* A POSE frame's integer fields from a call's arguments: args[at[0..2]] as int64 into ints, args[3]
 * (the time, us) as uint64; 1 when one would not fit (the encoding error the Python counts: the
 * caller returns None), 0 when all fit. */
static inline int ct_py_pose_ints(PyObject *const *args, const int *at, long long *ints, unsigned long long *t_us)
{
    int k;
    for (k = 0; k < 3; ++k) {
        int overflow = 0;
        ints[k] = PyLong_AsLongLongAndOverflow(args[at[k]], &overflow);
        if ((ints[k] == -1 && PyErr_Occurred()) || overflow) {
            PyErr_Clear();
            return 1;
        }
    }
    *t_us = PyLong_AsUnsignedLongLong(args[3]);
    if (*t_us == (unsigned long long)-1 && PyErr_Occurred()) {
        PyErr_Clear();
        return 1;
    }
    return 0;
}

/* The frame out[0 .. k - 1] (k < 0: one the wire format refused, not sent) numbered as
 * transmit.Transmitter._write_numbered numbers it: *seq counted on (mod 256) and the frame handed to
 * write; a refused frame or an Exception write raises counted in *errors (the exception cleared, as
 * there). -1 with the exception set where making the bytes failed or write raised what is not an
 * Exception (KeyboardInterrupt, SystemExit: not a link's failure), else 0. */
static inline int ct_py_write_numbered(PyObject *write, const uint8_t *out, int k, int64_t *seq, int64_t *errors)
{
    PyObject *frame, *r;
    if (k < 0) {
        ++*errors;
        return 0;
    }
    frame = PyBytes_FromStringAndSize((const char *)out, k);
    if (frame == NULL)
        return -1;
    *seq = (*seq + 1) & 0xFF;
    r = PyObject_CallOneArg(write, frame);
    Py_DECREF(frame);
    if (r == NULL) {
        if (!PyErr_ExceptionMatches(PyExc_Exception))
            return -1;
        PyErr_Clear();
        ++*errors;
        return 0;
    }
    Py_DECREF(r);
    return 0;
}

struct ct_sup;
/* o's supervisor state (py_supervise.c: a bound SupMag), for a kernel that chains its pose status; NULL
 * with a TypeError when o is none */
const struct ct_sup *ct_py_sup_of(PyObject *o);

/* o's ring and counters (py_multi.c: a bound SamplePush), for a kernel that pushes a channel's samples
 * itself (ct_sample_push's arguments): 0, or -1 with a TypeError when o is none */
int ct_py_sample_push_of(PyObject *o, int64_t **t, double **b, uint8_t **flags, int64_t *cap, int64_t **st,
                         int64_t **cnt);

#endif /* CT_PY_GLUE_H */
