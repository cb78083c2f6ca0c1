/*
 * CPython glue of the many-sensor kernels (src/multi.c): window_frame (one PULSE_WINDOW frame, as
 * Transmitter.pulse_window sends it), flip_frame (one MAG_FLIP_CMD, as Transmitter.mag_flip), sigma_from (SensorChannel.sigma_from) and the type
 * WindowColumn (SensorChannel.close_window, bound once at start-up to the channel's and its
 * extractor's buffers), WindowRun (WindowCloser.close_run: a pulse's windows on a run of channels, bound
 * to their WindowColumn objects) and SamplePush (SensorChannel.push, bound to the channel's sample ring).  METH_FASTCALL; they read their arguments in place and create no Python
 * object but the frames' bytes and the flags returned.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_pulse.h"

/* window_frame(seq, src, node, coil, pulse_id, first_us, last_us, n_used, n_base, flags) -> bytes or
 * None: one PULSE_WINDOW frame as encode_frame makes it (None: a value the wire format refuses) */
static PyObject *mul_window_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_WINDOW_FRAME_MAX];
    int64_t seq, src, f[8];
    uint64_t first, last;
    int k;
    static const int at[6] = {2, 3, 4, 7, 8, 9};
    (void)mod;
    if (nargs != 10) {
        PyErr_Format(PyExc_TypeError, "window_frame() takes 10 arguments (%zd given)", nargs);
        return NULL;
    }
    if (!ct_py_pack_q(args[0], &seq) || !ct_py_pack_q(args[1], &src)) {
        PyErr_SetString(PyExc_TypeError, "window_frame: seq and src must be integers");
        return NULL;
    }
    for (k = 0; k < 6; ++k)
        if (!ct_py_pack_q(args[at[k]], &f[k]))
            Py_RETURN_NONE;
    if (!ct_py_pack_Q(args[5], &first) || !ct_py_pack_Q(args[6], &last))
        Py_RETURN_NONE;
    k = ct_window_frame(out, (int)(seq & 0xFF), (int)(src & 0xFF), f[0], f[1], f[2], first, last, f[3], f[4], f[5]);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* flip_frame(seq, src, node, at_us, state) -> bytes or None: one MAG_FLIP_CMD frame as encode_frame
 * makes it (None: a value the wire format refuses) */
static PyObject *mul_flip_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_FLIP_FRAME_MAX];
    int64_t seq, src, node, state;
    uint64_t at;
    int k;
    (void)mod;
    if (nargs != 5) {
        PyErr_Format(PyExc_TypeError, "flip_frame() takes 5 arguments (%zd given)", nargs);
        return NULL;
    }
    if (!ct_py_pack_q(args[0], &seq) || !ct_py_pack_q(args[1], &src)) {
        PyErr_SetString(PyExc_TypeError, "flip_frame: seq and src must be integers");
        return NULL;
    }
    if (!ct_py_pack_q(args[2], &node) || !ct_py_pack_Q(args[3], &at) || !ct_py_pack_q(args[4], &state))
        Py_RETURN_NONE;
    k = ct_flip_frame(out, (int)(seq & 0xFF), (int)(src & 0xFF), node, at, state);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* a C-contiguous float64 buffer, or -1 with TypeError naming `what` */
static int mul_doubles(PyObject *obj, int writable, Py_buffer *v, const char *what)
{
    const char *f;
    if (PyObject_GetBuffer(obj, v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: needs a %sC-contiguous float64 buffer", what, writable ? "writable " : "");
        return -1;
    }
    f = v->format;
    if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<'))
        f++;
    if (f == NULL || f[0] != 'd' || f[1] != '\0' || v->itemsize != 8) {
        PyBuffer_Release(v);
        PyErr_Format(PyExc_TypeError, "%s: needs float64 items", what);
        return -1;
    }
    return 0;
}

/* sigma_from(var, sig, floor): sig = sqrt(max(var, floor)) item by item (sig may be var) */
static PyObject *mul_sigma_from(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vv, vs;
    double floor;
    (void)mod;
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "sigma_from() takes 3 arguments (%zd given)", nargs);
        return NULL;
    }
    floor = PyFloat_AsDouble(args[2]);
    if (floor == -1.0 && PyErr_Occurred())
        return NULL;
    if (mul_doubles(args[0], 0, &vv, "var") < 0)
        return NULL;
    if (mul_doubles(args[1], 1, &vs, "sig") < 0) {
        PyBuffer_Release(&vv);
        return NULL;
    }
    if (vv.len != vs.len) {
        PyBuffer_Release(&vv);
        PyBuffer_Release(&vs);
        PyErr_SetString(PyExc_ValueError, "sigma_from: var and sig differ in size");
        return NULL;
    }
    ct_sigma_from((int64_t)(vv.len / 8), (const double *)vv.buf, (double *)vs.buf, floor);
    PyBuffer_Release(&vv);
    PyBuffer_Release(&vs);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------- WindowColumn */
#define WC_NBUF 15
typedef struct {
    PyObject_HEAD
    struct ct_pulse x;
    struct ct_sample_ring r;
    struct ct_window_column c;
    Py_buffer views[WC_NBUF];
    int bound;
} WindowColumnObject;

static void WindowColumn_dealloc(WindowColumnObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < WC_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int WindowColumn_init(WindowColumnObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"t", "b", "flags", "used_t", "emp_var", "res", "ires", "S", "var", "wflags", "done",
                             "pulse_mid", "amp", "amp_var", "info", "settle_us", "fall_us", "baseline_us",
                             "guard_us", "min_pulse", "min_base", "max_gap_us", "max_samples", "drift_limit",
                             "sigma", "drift_nsigma", NULL};
    static const char *fmts[WC_NBUF] = {"qlL", "d", "B", "ql", "d", "d", "ql", "d", "d", "ql", "?", "ql", "d", "d",
                                        "ql"};
    static const int size[WC_NBUF] = {8, 8, 1, 8, 8, 8, 8, 8, 8, 8, 1, 8, 8, 8, 8};
    static const int writable[WC_NBUF] = {0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1};
    PyObject *o[WC_NBUF];
    long long st[8];     /* settle, fall, baseline, guard, min_pulse, min_base, max_gap, max_samples */
    double fl[3];        /* drift_limit, sigma, drift_nsigma */
    Py_ssize_t cap = 0, ncoil = 0, len;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOOOOOOOOOLLLLLLLLddd", kwlist, &o[0], &o[1], &o[2], &o[3],
                                     &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12], &o[13], &o[14],
                                     &st[0], &st[1], &st[2], &st[3], &st[4], &st[5], &st[6], &st[7], &fl[0], &fl[1], &fl[2]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "WindowColumn: already bound");
        return -1;
    }
    if (st[7] < 1) {
        PyErr_SetString(PyExc_ValueError, "WindowColumn: max_samples must be >= 1");
        return -1;
    }
    for (i = 0; i < WC_NBUF; ++i) {
        /* t sets the ring's capacity, wflags the coils; the rest is checked against them */
        switch (i) {
        case 0: len = 2; break;
        case 1: len = 3 * cap; break;
        case 2: len = cap; break;
        case 3: len = (Py_ssize_t)st[7]; break;
        case 4: case 12: case 13: len = 3; break;
        case 5: len = 6; break;
        case 6: case 14: len = 4; break;
        case 9: len = 1; break;
        case 7: case 8: len = 3 * ncoil; break;
        default: len = ncoil; break;
        }
        if (i == 7) {      /* the coils from wflags, bound out of order: S and var are 3 x n */
            Py_buffer fv;
            if (ct_py_buffer(o[9], 1, 8, fmts[9], 1, &fv, kwlist[9]) < 0) {
                while (--i >= 0)
                    PyBuffer_Release(&self->views[i]);
                return -1;
            }
            ncoil = fv.len / 8;
            PyBuffer_Release(&fv);
            len = 3 * ncoil;
        }
        if (ct_py_buffer(o[i], len, size[i], fmts[i], writable[i], &self->views[i], kwlist[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        if (i == 0)
            cap = self->views[0].len / 8;
    }
    ct_py_pulse_bind(&self->r, &self->x, self->views, cap, st, fl);
    self->c.n = (int64_t)ncoil;
    self->c.res = (double *)self->views[5].buf;
    self->c.ires = (int64_t *)self->views[6].buf;
    self->c.S = (double *)self->views[7].buf;
    self->c.V = (double *)self->views[8].buf;
    self->c.flags = (int64_t *)self->views[9].buf;
    self->c.done = (uint8_t *)self->views[10].buf;
    self->c.pulse_mid = (int64_t *)self->views[11].buf;
    self->c.amp = (double *)self->views[12].buf;
    self->c.amp_var = (double *)self->views[13].buf;
    self->c.info = (int64_t *)self->views[14].buf;
    self->bound = 1;
    return 0;
}

/* close(start_us, end_us, head, count, coil) -> flags */
static PyObject *WindowColumn_close(WindowColumnObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[5];
    int k;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "WindowColumn: not bound");
        return NULL;
    }
    if (nargs != 5) {
        PyErr_Format(PyExc_TypeError, "close() takes 5 arguments (%zd given)", nargs);
        return NULL;
    }
    for (k = 0; k < 5; ++k) {
        long long x = PyLong_AsLongLong(args[k]);
        if (x == -1 && PyErr_Occurred())
            return NULL;
        v[k] = (int64_t)x;
    }
    if (v[2] < 0 || v[2] >= self->r.cap || v[3] < 0 || v[3] > self->r.cap) {
        PyErr_SetString(PyExc_ValueError, "close: head or count outside the ring");
        return NULL;
    }
    if (v[4] < 0 || v[4] >= self->c.n) {
        PyErr_SetString(PyExc_ValueError, "close: coil outside the burst");
        return NULL;
    }
    self->r.head = v[2];
    self->r.count = v[3];
    return PyLong_FromLongLong(ct_window_column(&self->c, &self->x, &self->r, v[0], v[1], v[4]));
}

static PyMethodDef WindowColumn_methods[] = {
    {"close", (PyCFunction)(void (*)(void))WindowColumn_close, METH_FASTCALL,
     "close(start_us, end_us, head, count, coil) -> flags: SensorChannel.close_window over the bound ring (its "
     "head and count): the extraction into res, ires, the amplitude into amp, amp_var and column coil of the "
     "burst, (n_used, n_base, first, last) into info"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject WindowColumnType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.WindowColumn",
    .tp_basicsize = sizeof(WindowColumnObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "WindowColumn(t, b, flags, used_t, emp_var, res, ires, S, var, wflags, done, pulse_mid, amp, amp_var, "
              "info, settle_us, fall_us, baseline_us, guard_us, min_pulse, min_base, max_gap_us, max_samples, "
              "drift_limit, sigma, drift_nsigma): a pulse extractor bound to its ring, its scratch and a sensor "
              "channel's burst, closing one window into its column per call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)WindowColumn_init,
    .tp_dealloc = (destructor)WindowColumn_dealloc,
    .tp_methods = WindowColumn_methods,
};

/* ------------------------------------------------------------- SamplePush */
#define SP_NBUF 5
typedef struct {
    PyObject_HEAD
    int64_t *t, *st, *cnt;
    double *b;
    uint8_t *flags;
    int64_t cap;
    Py_buffer views[SP_NBUF];
    int bound;
} SamplePushObject;

static void SamplePush_dealloc(SamplePushObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < SP_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int SamplePush_init(SamplePushObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"t", "b", "flags", "state", "counts", NULL};
    static const char *fmts[SP_NBUF] = {"qlL", "d", "B", "qlL", "qlL"};
    static const int size[SP_NBUF] = {8, 8, 1, 8, 8};
    PyObject *o[SP_NBUF];
    Py_ssize_t cap = 0, len;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOO", kwlist, &o[0], &o[1], &o[2], &o[3], &o[4]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SamplePush: already bound");
        return -1;
    }
    for (i = 0; i < SP_NBUF; ++i) {
        len = i == 0 ? 2 : i == 1 ? 3 * cap : i == 2 ? cap : i == 3 ? 4 : 2;
        if (ct_py_buffer(o[i], len, size[i], fmts[i], 1, &self->views[i], kwlist[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        if (i == 0)
            cap = self->views[0].len / 8;
    }
    if (self->views[1].len != 3 * cap * 8 || self->views[2].len != cap) {
        for (i = 0; i < SP_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
        PyErr_SetString(PyExc_ValueError, "SamplePush: t, b (cap x 3) and flags differ in capacity");
        return -1;
    }
    self->t = (int64_t *)self->views[0].buf;
    self->b = (double *)self->views[1].buf;
    self->flags = (uint8_t *)self->views[2].buf;
    self->st = (int64_t *)self->views[3].buf;
    self->cnt = (int64_t *)self->views[4].buf;
    self->cap = (int64_t)cap;
    self->bound = 1;
    return 0;
}

/* an exact int into *v; 0 for anything else or one beyond int64 */
static int sp_int(PyObject *o, long long *v)
{
    int overflow = 0;
    if (!PyLong_CheckExact(o))
        return 0;
    *v = PyLong_AsLongLongAndOverflow(o, &overflow);
    if (overflow || (*v == -1 && PyErr_Occurred())) {
        PyErr_Clear();
        return 0;
    }
    return 1;
}

/* Python's count * lsb for an exact int count (exactly a double: |count| <= 2**53) or an exact float:
 * 1 with the product in *x, else 0 */
static int sp_scaled(PyObject *o, double lsb, double *x)
{
    long long v;
    if (PyFloat_CheckExact(o)) {
        *x = PyFloat_AS_DOUBLE(o) * lsb;
        return 1;
    }
    if (!sp_int(o, &v) || v > (1LL << 53) || v < -(1LL << 53))
        return 0;
    *x = (double)v * lsb;
    return 1;
}

/* push(t_us, x, y, z, flip, lsb) -> 1 (pushed), 0 (refused, counted) or -1 (an argument of another kind:
 * nothing done, the caller's Python reference takes the sample) */
static PyObject *SamplePush_push(SamplePushObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long t, flip;
    double x, y, z, lsb;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SamplePush: not bound");
        return NULL;
    }
    if (nargs != 6) {
        PyErr_Format(PyExc_TypeError, "push() takes 6 arguments (%zd given)", nargs);
        return NULL;
    }
    if (!PyFloat_CheckExact(args[5]))
        return PyLong_FromLong(-1);
    lsb = PyFloat_AS_DOUBLE(args[5]);
    if (!sp_int(args[0], &t) || !sp_int(args[4], &flip) || !sp_scaled(args[1], lsb, &x) ||
        !sp_scaled(args[2], lsb, &y) || !sp_scaled(args[3], lsb, &z))
        return PyLong_FromLong(-1);
    if (self->st[0] < 0 || self->st[0] >= self->cap || self->st[1] < 0 || self->st[1] > self->cap) {
        PyErr_SetString(PyExc_ValueError, "push: head or count outside the ring");
        return NULL;
    }
    return PyLong_FromLong(ct_sample_push(self->t, self->b, self->flags, self->cap, self->st, self->cnt,
                                          (int64_t)t, x, y, z, (flip & 2) != 0, (int)(flip & 1)));
}

static PyMethodDef SamplePush_methods[] = {
    {"push", (PyCFunction)(void (*)(void))SamplePush_push, METH_FASTCALL,
     "push(t_us, x, y, z, flip, lsb) -> 1, 0 or -1: SensorChannel.push of one magnetometer sample (counts x, y, z "
     "of lsb tesla; flip bit0 set/reset, bit1 saturated) into the bound ring: 1 pushed, 0 refused and counted, -1 "
     "an argument the kernel does not take (nothing done)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SamplePushType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SamplePush",
    .tp_basicsize = sizeof(SamplePushObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SamplePush(t, b, flags, state, counts): a sensor channel's sample ring (SampleRing's t, b, flags and "
              "its state hc = head, count, latest, rejected) and the channel's counters (samples, changes), "
              "taking one magnetometer sample per call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SamplePush_init,
    .tp_dealloc = (destructor)SamplePush_dealloc,
    .tp_methods = SamplePush_methods,
};

static PyMethodDef multi_functions[] = {
    {"window_frame", (PyCFunction)(void (*)(void))mul_window_frame, METH_FASTCALL,
     "window_frame(seq, src, node, coil, pulse_id, first_us, last_us, n_used, n_base, flags) -> bytes or None: "
     "one PULSE_WINDOW frame as encode_frame makes it (None: a value the wire format refuses)"},
    {"flip_frame", (PyCFunction)(void (*)(void))mul_flip_frame, METH_FASTCALL,
     "flip_frame(seq, src, node, at_us, state) -> bytes or None: one MAG_FLIP_CMD frame as encode_frame makes it "
     "(None: a value the wire format refuses)"},
    {"sigma_from", (PyCFunction)(void (*)(void))mul_sigma_from, METH_FASTCALL,
     "sigma_from(var, sig, floor): sig = sqrt(max(var, floor)) item by item (SensorChannel.sigma_from)"},
    {NULL, NULL, 0, NULL}};

int ct_py_sample_push_of(PyObject *o, int64_t **t, double **b, uint8_t **flags, int64_t *cap, int64_t **st,
                         int64_t **cnt)
{
    SamplePushObject *p = (SamplePushObject *)o;
    if (!PyObject_TypeCheck(o, &SamplePushType) || !p->bound) {
        PyErr_SetString(PyExc_TypeError, "a bound SamplePush is needed");
        return -1;
    }
    *t = p->t;
    *b = p->b;
    *flags = p->flags;
    *cap = p->cap;
    *st = p->st;
    *cnt = p->cnt;
    return 0;
}

/* ------------------------------------------------------------- WindowRun */
typedef struct {
    PyObject_HEAD
    PyObject *cols;                 /* the channels' WindowColumn objects (tuple, held) */
    Py_ssize_t n;
    const struct ct_window_column **c;
    const struct ct_pulse **x;
    struct ct_sample_ring **r;
    const int64_t **hc;
    int64_t **cnt;
    int64_t *flags;
    Py_buffer *views;               /* hc and counts per channel, then flags */
    Py_ssize_t nv;
} WindowRunObject;

static void WindowRun_dealloc(WindowRunObject *self)
{
    Py_ssize_t k;
    for (k = 0; k < self->nv; ++k)
        PyBuffer_Release(&self->views[k]);
    PyMem_Free(self->views);
    PyMem_Free((void *)self->c);
    PyMem_Free((void *)self->x);
    PyMem_Free(self->r);
    PyMem_Free((void *)self->hc);
    PyMem_Free(self->cnt);
    Py_XDECREF(self->cols);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int WindowRun_init(WindowRunObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"columns", "states", "counts", "flags", NULL};
    PyObject *cols, *hcs, *cnts, *fl;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOO", kwlist, &cols, &hcs, &cnts, &fl))
        return -1;
    if (self->cols != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "WindowRun: already bound");
        return -1;
    }
    if (!PyTuple_Check(cols) || !PyTuple_Check(hcs) || !PyTuple_Check(cnts)) {
        PyErr_SetString(PyExc_TypeError, "WindowRun: columns, states and counts must be tuples");
        return -1;
    }
    n = PyTuple_GET_SIZE(cols);
    if (n < 1 || PyTuple_GET_SIZE(hcs) != n || PyTuple_GET_SIZE(cnts) != n) {
        PyErr_SetString(PyExc_ValueError, "WindowRun: one column, state and counts per channel (at least one)");
        return -1;
    }
    for (k = 0; k < n; ++k)
        if (!PyObject_TypeCheck(PyTuple_GET_ITEM(cols, k), &WindowColumnType) ||
            !((WindowColumnObject *)PyTuple_GET_ITEM(cols, k))->bound) {
            PyErr_SetString(PyExc_TypeError, "WindowRun: columns must be bound WindowColumn objects");
            return -1;
        }
    self->c = PyMem_Calloc((size_t)n, sizeof(*self->c));
    self->x = PyMem_Calloc((size_t)n, sizeof(*self->x));
    self->r = PyMem_Calloc((size_t)n, sizeof(*self->r));
    self->hc = PyMem_Calloc((size_t)n, sizeof(*self->hc));
    self->cnt = PyMem_Calloc((size_t)n, sizeof(*self->cnt));
    self->views = PyMem_Calloc((size_t)(2 * n + 1), sizeof(Py_buffer));
    if (!self->c || !self->x || !self->r || !self->hc || !self->cnt || !self->views) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        WindowColumnObject *w = (WindowColumnObject *)PyTuple_GET_ITEM(cols, k);
        if (ct_py_buffer(PyTuple_GET_ITEM(hcs, k), 2, 8, "qlL", 0, &self->views[self->nv], "WindowRun states") < 0)
            return -1;
        self->hc[k] = (const int64_t *)self->views[self->nv++].buf;
        if (ct_py_buffer(PyTuple_GET_ITEM(cnts, k), 2, 8, "ql", 1, &self->views[self->nv], "WindowRun counts") < 0)
            return -1;
        self->cnt[k] = (int64_t *)self->views[self->nv++].buf;
        self->c[k] = &w->c;
        self->x[k] = &w->x;
        self->r[k] = &w->r;
    }
    if (ct_py_buffer(fl, n, 8, "ql", 1, &self->views[self->nv], "WindowRun flags") < 0)
        return -1;
    self->flags = (int64_t *)self->views[self->nv++].buf;
    Py_INCREF(cols);
    self->cols = cols;
    self->n = n;
    return 0;
}

/* close(coil, start_us, end_us, c0, c1) -> flagged: the window closed on channels c0..c1-1
 * (ct_window_run), each one's flags into the bound flags array */
static PyObject *WindowRun_close(WindowRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[5];
    Py_ssize_t i;
    int k;
    if (self->cols == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "WindowRun: not bound");
        return NULL;
    }
    if (ct_py_nargs("close", nargs, 5) < 0)
        return NULL;
    for (k = 0; k < 5; ++k)
        if (ct_py_int64(args[k], &v[k]) < 0)
            return NULL;
    if (v[3] < 0 || v[4] > self->n || v[3] > v[4]) {
        PyErr_SetString(PyExc_ValueError, "close: channels outside the bound ones");
        return NULL;
    }
    for (i = (Py_ssize_t)v[3]; i < (Py_ssize_t)v[4]; ++i) {
        if (v[0] < 0 || v[0] >= self->c[i]->n) {
            PyErr_SetString(PyExc_ValueError, "close: coil outside the burst");
            return NULL;
        }
        if (self->hc[i][0] < 0 || self->hc[i][0] >= self->r[i]->cap || self->hc[i][1] < 0 ||
            self->hc[i][1] > self->r[i]->cap) {
            PyErr_SetString(PyExc_ValueError, "close: head or count outside the ring");
            return NULL;
        }
    }
    return PyLong_FromLongLong(ct_window_run(self->c, self->x, self->r, self->hc, self->cnt, self->flags, v[3], v[4],
                                             v[1], v[2], v[0]));
}

static PyMethodDef WindowRun_methods[] = {
    {"close", (PyCFunction)(void (*)(void))WindowRun_close, METH_FASTCALL,
     "close(coil, start_us, end_us, c0, c1) -> flagged: WindowCloser.close_run's windows on channels c0..c1-1, each "
     "as WindowColumn.close at its ring's present head and count, its channel's changes counted, its flags into "
     "the bound flags array; the number flagged"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject WindowRunType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.WindowRun",
    .tp_basicsize = sizeof(WindowRunObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "WindowRun(columns, states, counts, flags): the sensor channels' WindowColumn objects, their rings' "
              "state arrays (SampleRing.hc), their counters (SensorChannel.cnt) and one int64 flags item per "
              "channel, bound once: a pulse's windows closed on a run of channels in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)WindowRun_init,
    .tp_dealloc = (destructor)WindowRun_dealloc,
    .tp_methods = WindowRun_methods,
};

int ct_register_multi(PyObject *m)
{
    if (PyModule_AddFunctions(m, multi_functions) < 0 || ct_py_add_type(m, &WindowColumnType, "WindowColumn") < 0 ||
        ct_py_add_type(m, &SamplePushType, "SamplePush") < 0 || ct_py_add_type(m, &WindowRunType, "WindowRun") < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "WINDOW_ID", CT_WINDOW_ID) < 0 ||
        PyModule_AddIntConstant(m, "WINDOW_PAYLOAD", CT_WINDOW_PAYLOAD) < 0 ||
        PyModule_AddIntConstant(m, "WINDOW_CRC_EXTRA", CT_WINDOW_CRC_EXTRA) < 0 ||
        PyModule_AddIntConstant(m, "FLIP_ID", CT_FLIP_ID) < 0 ||
        PyModule_AddIntConstant(m, "FLIP_PAYLOAD", CT_FLIP_PAYLOAD) < 0 ||
        PyModule_AddIntConstant(m, "FLIP_CRC_EXTRA", CT_FLIP_CRC_EXTRA) < 0)
        return -1;
    return 0;
}
