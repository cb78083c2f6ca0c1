/*
 * CPython glue of the per-tick scans over many sensors (src/ahead.c) and a run's PULSE_WINDOWs
 * (src/multi.c ct_window_frame).  ReadyUpto binds the channels' ring states once and its
 * upto(start, end, now, first) is measure.windows.WindowCloser.ready_upto; WindowFrames binds the
 * channels' window info, node ids and a run's flags once and its send(...) writes a run's frames as
 * WindowCloser.close_one sends them.  The type AheadScan binds every
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
    if (!ct_py_int_only(args[0], &b) || !ct_py_int_only(args[1], &j) || !ct_py_int_only(args[2], &start) || !ct_py_int_only(args[3], &end))
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

/* ------------------------------------------------------------- ReadyUpto */
typedef struct {
    PyObject_HEAD
    Py_buffer *views;
    Py_ssize_t nv, n;
    const int64_t **hc;
    const int64_t *extra;
    int64_t fall, baseline, timeout;
} ReadyUptoObject;

static void ReadyUpto_release(ReadyUptoObject *self)
{
    Py_ssize_t k;
    for (k = 0; k < self->nv; ++k)
        PyBuffer_Release(&self->views[k]);
    PyMem_Free(self->views);
    self->views = NULL;
    self->nv = 0;
}

static void ReadyUpto_dealloc(ReadyUptoObject *self)
{
    ReadyUpto_release(self);
    PyMem_Free((void *)self->hc);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ReadyUpto_init(ReadyUptoObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"states", "extra", "fall", "baseline", "timeout", NULL};
    PyObject *th, *ox;
    long long fall, base, tmo;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOLLL", kwlist, &th, &ox, &fall, &base, &tmo))
        return -1;
    if (self->views != NULL || self->hc != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ReadyUpto: already bound");
        return -1;
    }
    if (!PyTuple_Check(th) || (n = PyTuple_GET_SIZE(th)) < 1) {
        PyErr_SetString(PyExc_TypeError, "ReadyUpto: states needs a tuple of at least one ring's state");
        return -1;
    }
    self->views = PyMem_Calloc((size_t)(n + 1), sizeof(Py_buffer));
    self->hc = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    if (!self->views || !self->hc) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        if (ct_py_buffer(PyTuple_GET_ITEM(th, k), 3, 8, "ql", 0, &self->views[self->nv], "ReadyUpto states") < 0)
            goto fail;
        self->hc[k] = self->views[self->nv++].buf;
    }
    if (ct_py_buffer(ox, n, 8, "ql", 0, &self->views[self->nv], "ReadyUpto extra") < 0)
        goto fail;
    self->extra = self->views[self->nv++].buf;
    self->n = n;
    self->fall = (int64_t)fall;
    self->baseline = (int64_t)base;
    self->timeout = (int64_t)tmo;
    return 0;
fail:
    ReadyUpto_release(self);
    return -1;
}

/* upto(start, end, now_us, first) -> int: WindowCloser.ready_upto (-3: ask the reference) */
static PyObject *ReadyUpto_upto(ReadyUptoObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t start, end, now, first;
    if (ct_py_nargs("upto", nargs, 4) < 0)
        return NULL;
    if (self->views == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ReadyUpto: not bound");
        return NULL;
    }
    if (!ct_py_int_only(args[0], &start) || !ct_py_int_only(args[1], &end) || !ct_py_int_only(args[2], &now) || !ct_py_int_only(args[3], &first))
        return PyLong_FromLong(CT_AHEAD_ASK);
    return PyLong_FromLongLong((long long)ct_ready_upto(self->hc, self->extra, (int64_t)self->n, start, end, now, first,
                                                        self->fall, self->baseline, self->timeout));
}

static PyMethodDef ReadyUpto_methods[] = {
    {"upto", (PyCFunction)(void (*)(void))ReadyUpto_upto, METH_FASTCALL,
     "upto(start, end, now_us, first) -> int: measure.windows.WindowCloser.ready_upto"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject ReadyUptoType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ReadyUpto",
    .tp_basicsize = sizeof(ReadyUptoObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ReadyUpto(states, extra, fall, baseline, timeout): the channels' ring states (int64, >= 3: head, "
              "count, latest) and their extractors' fall + baseline (int64 array), the closer's fall, baseline and "
              "timeout (us), bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ReadyUpto_init,
    .tp_dealloc = (destructor)ReadyUpto_dealloc,
    .tp_methods = ReadyUpto_methods,
};

/* ------------------------------------------------------------- WindowFrames */
typedef struct {
    PyObject_HEAD
    Py_buffer *views;
    Py_ssize_t nv, n;
    const int64_t **info;
    const int64_t *nodes, *flags;
} WindowFramesObject;

static void WindowFrames_release(WindowFramesObject *self)
{
    Py_ssize_t k;
    for (k = 0; k < self->nv; ++k)
        PyBuffer_Release(&self->views[k]);
    PyMem_Free(self->views);
    self->views = NULL;
    self->nv = 0;
}

static void WindowFrames_dealloc(WindowFramesObject *self)
{
    WindowFrames_release(self);
    PyMem_Free((void *)self->info);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int WindowFrames_init(WindowFramesObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"infos", "nodes", "flags", NULL};
    PyObject *ti, *on, *of;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOO", kwlist, &ti, &on, &of))
        return -1;
    if (self->views != NULL || self->info != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "WindowFrames: already bound");
        return -1;
    }
    if (!PyTuple_Check(ti) || (n = PyTuple_GET_SIZE(ti)) < 1) {
        PyErr_SetString(PyExc_TypeError, "WindowFrames: infos needs a tuple of at least one channel's info");
        return -1;
    }
    self->views = PyMem_Calloc((size_t)(n + 2), sizeof(Py_buffer));
    self->info = PyMem_Calloc((size_t)n, sizeof(int64_t *));
    if (!self->views || !self->info) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        if (ct_py_buffer(PyTuple_GET_ITEM(ti, k), 4, 8, "ql", 0, &self->views[self->nv], "WindowFrames infos") < 0)
            goto fail;
        self->info[k] = self->views[self->nv++].buf;
    }
    if (ct_py_buffer(on, n, 8, "ql", 0, &self->views[self->nv], "WindowFrames nodes") < 0)
        goto fail;
    self->nodes = self->views[self->nv++].buf;
    if (ct_py_buffer(of, n, 8, "ql", 0, &self->views[self->nv], "WindowFrames flags") < 0)
        goto fail;
    self->flags = self->views[self->nv++].buf;
    self->n = n;
    return 0;
fail:
    WindowFrames_release(self);
    return -1;
}

/* send(write, seq, src, coil, pulse_id, c0, c1) -> int or None: for channels c0 .. c1 - 1 in order,
 * the PULSE_WINDOW that measure.windows.WindowCloser.close_one sends (its info: n_used, n_base clipped
 * at 255, first, last; its flags & 0xFF) built by ct_window_frame with the sequence seq counted on
 * as transmit.Transmitter._write_numbered counts it, and handed to write (an Exception it raises
 * counted as a tx error, as there); a frame the wire format refuses counted as a tx error, not sent.
 * Returns errors << 8 | the next seq; None for a coil or pulse id that is not an int64, or a run out
 * of the channels (the caller's reference sends them). */
static PyObject *WindowFrames_send(WindowFramesObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t seq, src, coil, pid, c0, c1, i, errors = 0;
    uint8_t out[CT_WINDOW_FRAME_MAX];
    if (ct_py_nargs("send", nargs, 7) < 0)
        return NULL;
    if (self->views == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "WindowFrames: not bound");
        return NULL;
    }
    if (!ct_py_int_only(args[1], &seq) || !ct_py_int_only(args[2], &src) || !ct_py_int_only(args[3], &coil) || !ct_py_int_only(args[4], &pid) ||
        !ct_py_int_only(args[5], &c0) || !ct_py_int_only(args[6], &c1) || c0 < 0 || c1 > (int64_t)self->n || c0 > c1)
        Py_RETURN_NONE;
    for (i = c0; i < c1; ++i) {
        const int64_t *iv = self->info[i];
        int64_t n_used = iv[0] < 255 ? iv[0] : 255, n_base = iv[1] < 255 ? iv[1] : 255;
        int k = -1;
        if (iv[2] >= 0 && iv[3] >= 0)       /* first, last: 'Q' (a negative one refused, as struct.pack) */
            k = ct_window_frame(out, (int)(seq & 0xFF), (int)(src & 0xFF), self->nodes[i], coil, pid, (uint64_t)iv[2],
                                (uint64_t)iv[3], n_used, n_base, self->flags[i] & 0xFF);
        if (ct_py_write_numbered(args[0], out, k, &seq, &errors) < 0)
            return NULL;
    }
    return PyLong_FromLongLong((long long)((errors << 8) | (seq & 0xFF)));
}

static PyMethodDef WindowFrames_methods[] = {
    {"send", (PyCFunction)(void (*)(void))WindowFrames_send, METH_FASTCALL,
     "send(write, seq, src, coil, pulse_id, c0, c1) -> int or None: a run's PULSE_WINDOWs written "
     "(errors << 8 | next seq)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject WindowFramesType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.WindowFrames",
    .tp_basicsize = sizeof(WindowFramesObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "WindowFrames(infos, nodes, flags): the channels' last windows' info (int64, 4: n_used, n_base, first, "
              "last), their node ids and the run's window flags (int64 arrays), bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)WindowFrames_init,
    .tp_dealloc = (destructor)WindowFrames_dealloc,
    .tp_methods = WindowFrames_methods,
};

int ct_register_ahead(PyObject *m)
{
    if (ct_py_add_type(m, &ReadyUptoType, "ReadyUpto") < 0 || ct_py_add_type(m, &WindowFramesType, "WindowFrames") < 0)
        return -1;
    return ct_py_add_type(m, &AheadScanType, "AheadScan");
}
