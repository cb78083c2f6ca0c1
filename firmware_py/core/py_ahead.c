/*
 * CPython glue of solving ahead for many sensors (src/ahead.c): the type AheadScan binds every
 * sensor channel's closed flags, counters and sample ring, each sensor's wish (an int64 entry),
 * the tracker's turns (nch x 2) and marks (nch) once (start-up); its scan(burst, j, start, end) is
 * track.magnetic.MagneticTracker._ahead_scan.  METH_FASTCALL; no Python object is created per call
 * but the small int returned.  The buffer tables are allocated once, at construction.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

typedef struct {
    PyObject_HEAD
    Py_buffer *views;
    Py_ssize_t nv;
    struct ct_ahead_scan s;
    const uint8_t **done;
    const int64_t **cnt, **t, **hc, **want;
    int64_t *cap, *want_at;
} AheadScanObject;

static void AheadScan_release(AheadScanObject *self)
{
    Py_ssize_t k;
    for (k = 0; k < self->nv; ++k)
        PyBuffer_Release(&self->views[k]);
    PyMem_Free(self->views);
    self->views = NULL;
    self->nv = 0;
}

static void AheadScan_dealloc(AheadScanObject *self)
{
    AheadScan_release(self);
    PyMem_Free((void *)self->done);
    PyMem_Free((void *)self->cnt);
    PyMem_Free((void *)self->t);
    PyMem_Free((void *)self->hc);
    PyMem_Free((void *)self->want);
    PyMem_Free(self->cap);
    PyMem_Free(self->want_at);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* bind obj (n items of itemsize, formats) as the next view; its buffer, or NULL with the error set */
static void *ah_bind(AheadScanObject *self, PyObject *obj, Py_ssize_t n, Py_ssize_t itemsize, const char *formats,
                     int writable, const char *what, Py_ssize_t *len)
{
    Py_buffer *v = &self->views[self->nv];
    if (ct_py_buffer(obj, n, itemsize, formats, writable, v, what) < 0)
        return NULL;
    self->nv++;
    if (len != NULL)
        *len = v->len / itemsize;
    return v->buf;
}

static int ah_tuple(PyObject *o, Py_ssize_t n, const char *what)
{
    if (!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != n) {
        PyErr_Format(PyExc_TypeError, "AheadScan: %s needs a tuple of one item per channel", what);
        return -1;
    }
    return 0;
}

static int AheadScan_init(AheadScanObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"done", "counts", "times", "states", "extra", "want", "want_at", "turns", "marks", NULL};
    PyObject *td, *tc, *tt, *th, *ox, *tw, *ta, *os, *oi;
    Py_ssize_t n, k, ncoils = -1, len;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOOO", kwlist, &td, &tc, &tt, &th, &ox, &tw, &ta, &os, &oi))
        return -1;
    if (self->views != NULL || self->done != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "AheadScan: already bound");
        return -1;
    }
    if (!PyTuple_Check(td) || (n = PyTuple_GET_SIZE(td)) < 1) {
        PyErr_SetString(PyExc_TypeError, "AheadScan: done needs a tuple of at least one channel's flags");
        return -1;
    }
    if (ah_tuple(tc, n, "counts") < 0 || ah_tuple(tt, n, "times") < 0 || ah_tuple(th, n, "states") < 0 ||
        ah_tuple(tw, n, "want") < 0 || ah_tuple(ta, n, "want_at") < 0)
        return -1;
    self->views = PyMem_Calloc((size_t)(5 * n + 3), sizeof(Py_buffer));
    self->done = PyMem_Calloc((size_t)n, sizeof(uint8_t *));
    self->cnt = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    self->t = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    self->hc = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    self->want = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    self->cap = PyMem_Calloc((size_t)n, sizeof(int64_t));
    self->want_at = PyMem_Calloc((size_t)n, sizeof(int64_t));
    if (!self->views || !self->done || !self->cnt || !self->t || !self->hc || !self->want || !self->cap ||
        !self->want_at) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        Py_ssize_t nw;
        long long at;
        if (!(self->done[k] = ah_bind(self, PyTuple_GET_ITEM(td, k), 1, 1, "?B", 0, "AheadScan done", &len)))
            goto fail;
        if (ncoils < 0)
            ncoils = len;
        if (len != ncoils) {
            PyErr_SetString(PyExc_ValueError, "AheadScan: every channel's done has the same coils");
            goto fail;
        }
        if (!(self->cnt[k] = ah_bind(self, PyTuple_GET_ITEM(tc, k), 2, 8, "ql", 0, "AheadScan counts", NULL)) ||
            !(self->t[k] = ah_bind(self, PyTuple_GET_ITEM(tt, k), 1, 8, "ql", 0, "AheadScan times", &len)))
            goto fail;
        self->cap[k] = (int64_t)len;
        if (!(self->hc[k] = ah_bind(self, PyTuple_GET_ITEM(th, k), 3, 8, "ql", 0, "AheadScan states", NULL)) ||
            !(self->want[k] = ah_bind(self, PyTuple_GET_ITEM(tw, k), 1, 8, "ql", 0, "AheadScan want", &nw)))
            goto fail;
        at = PyLong_AsLongLong(PyTuple_GET_ITEM(ta, k));
        if (at == -1 && PyErr_Occurred())
            goto fail;
        if (at < 0 || at >= nw) {
            PyErr_SetString(PyExc_ValueError, "AheadScan: want_at out of its array");
            goto fail;
        }
        self->want_at[k] = (int64_t)at;
    }
    if (!(self->s.extra = ah_bind(self, ox, n, 8, "ql", 0, "AheadScan extra", NULL)) ||
        !(self->s.st = ah_bind(self, os, 2 * n, 8, "ql", 1, "AheadScan turns", NULL)) ||
        !(self->s.idle = ah_bind(self, oi, n, 8, "ql", 1, "AheadScan marks", NULL)))
        goto fail;
    self->s.nch = (int64_t)n;
    self->s.n = (int64_t)ncoils;
    self->s.done = self->done;
    self->s.cnt = self->cnt;
    self->s.t = self->t;
    self->s.hc = self->hc;
    self->s.cap = self->cap;
    self->s.want = self->want;
    self->s.want_at = self->want_at;
    return 0;
fail:
    AheadScan_release(self);
    return -1;
}

/* an int argument into *x: 1, or 0 (error cleared) when it is not an int64 */
static int ah_int(PyObject *o, int64_t *x)
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

/* scan(burst, j, start, end) -> int: MagneticTracker._ahead_scan (-3: ask the reference) */
static PyObject *AheadScan_scan(AheadScanObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t b, j, start, end;
    if (ct_py_nargs("scan", nargs, 4) < 0)
        return NULL;
    if (self->views == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "AheadScan: not bound");
        return NULL;
    }
    if (!ah_int(args[0], &b) || !ah_int(args[1], &j) || !ah_int(args[2], &start) || !ah_int(args[3], &end))
        return PyLong_FromLong(CT_AHEAD_ASK);
    return PyLong_FromLongLong((long long)ct_ahead_scan(&self->s, b, j, start, end));
}

static PyMethodDef AheadScan_methods[] = {
    {"scan", (PyCFunction)(void (*)(void))AheadScan_scan, METH_FASTCALL,
     "scan(burst, j, start, end) -> int: track.magnetic.MagneticTracker._ahead_scan"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject AheadScanType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.AheadScan",
    .tp_basicsize = sizeof(AheadScanObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "AheadScan(done, counts, times, states, extra, want, want_at, turns, marks): per channel its closed "
              "flags (bool, coils), counters (int64, 2), ring times and state (int64), extractor's fall + baseline "
              "(int64 array), wish (int64 array, entry want_at: wanted when 0); the tracker's turns (int64 nch x 2) and "
              "marks (int64 nch), bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)AheadScan_init,
    .tp_dealloc = (destructor)AheadScan_dealloc,
    .tp_methods = AheadScan_methods,
};

int ct_register_ahead(PyObject *m)
{
    return ct_py_add_type(m, &AheadScanType, "AheadScan");
}
