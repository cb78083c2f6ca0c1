/*
 * CPython glue of the window extraction and the pose solve's bookkeeping (src/window.c): the
 * types PulseWindow and SolveIO, bound once (start-up) to the caller's numpy arrays; their
 * per-call methods (METH_FASTCALL) take ints and the solve's input arrays, write into the bound
 * buffers and create no Python object.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_pulse.h"

/* a C-contiguous buffer of at least n items of `size` bytes whose format is one of `fmts`, or -1
 * with TypeError naming `what` */
/* ------------------------------------------------------------- PulseWindow */
#define PW_NBUF 7
typedef struct {
    PyObject_HEAD
    struct ct_pulse x;
    struct ct_sample_ring r;
    double *res;                 /* amp (3), var (3) of the last extract */
    int64_t *ires;               /* flags, n_pulse, n_base, n_rec */
    Py_buffer views[PW_NBUF];
    int bound;
} PulseWindowObject;

static void PulseWindow_dealloc(PulseWindowObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < PW_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int PulseWindow_init(PulseWindowObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"t", "b", "flags", "used_t", "emp_var", "res", "ires", "settle_us", "fall_us",
                             "baseline_us", "guard_us", "min_pulse", "min_base", "max_gap_us", "max_samples",
                             "drift_limit", "sigma", "drift_nsigma", NULL};
    static const char *names[PW_NBUF] = {"t", "b", "flags", "used_t", "emp_var", "res", "ires"};
    static const char *fmts[PW_NBUF] = {"qlL", "d", "B", "ql", "d", "d", "ql"};
    static const int size[PW_NBUF] = {8, 8, 1, 8, 8, 8, 8};
    static const int writable[PW_NBUF] = {0, 0, 0, 1, 1, 1, 1};
    PyObject *o[PW_NBUF];
    long long st[8];     /* settle, fall, baseline, guard, min_pulse, min_base, max_gap, max_samples */
    double fl[3];        /* drift_limit, sigma, drift_nsigma */
    Py_ssize_t cap = 0, len[PW_NBUF];
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOLLLLLLLLddd", kwlist, &o[0], &o[1], &o[2], &o[3], &o[4],
                                     &o[5], &o[6], &st[0], &st[1], &st[2], &st[3], &st[4], &st[5], &st[6], &st[7],
                                     &fl[0], &fl[1], &fl[2]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "PulseWindow: already bound");
        return -1;
    }
    if (st[7] < 1) {
        PyErr_SetString(PyExc_ValueError, "PulseWindow: max_samples must be >= 1");
        return -1;
    }
    for (i = 0; i < PW_NBUF; ++i) {
        len[i] = i == 0 ? 2 : i == 1 ? 3 * cap : i == 2 ? cap : i == 3 ? (Py_ssize_t)st[7] : i == 4 ? 3 : i == 5 ? 6 : 4;
        if (ct_py_buffer(o[i], len[i], size[i], fmts[i], writable[i], &self->views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        if (i == 0)
            cap = self->views[0].len / 8;
    }
    ct_py_pulse_bind(&self->r, &self->x, self->views, cap, st, fl);
    self->res = (double *)self->views[5].buf;
    self->ires = (int64_t *)self->views[6].buf;
    self->bound = 1;
    return 0;
}

/* extract(start_us, end_us, head, count) -> flags: the window over the ring's state (head, count) */
static PyObject *PulseWindow_extract(PulseWindowObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t start, end, head, count;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "PulseWindow: not bound");
        return NULL;
    }
    if (nargs != 4) {
        PyErr_Format(PyExc_TypeError, "extract() takes 4 arguments (%zd given)", nargs);
        return NULL;
    }
    if (ct_py_int64(args[0], &start) < 0 || ct_py_int64(args[1], &end) < 0 || ct_py_int64(args[2], &head) < 0 ||
        ct_py_int64(args[3], &count) < 0)
        return NULL;
    if (head < 0 || head >= self->r.cap || count < 0 || count > self->r.cap) {
        PyErr_SetString(PyExc_ValueError, "extract: head or count outside the ring");
        return NULL;
    }
    self->r.head = head;
    self->r.count = count;
    return PyLong_FromLongLong(ct_pulse_extract(&self->x, &self->r, start, end, self->res, self->res + 3,
                                                self->ires));
}

static PyMethodDef PulseWindow_methods[] = {
    {"extract", (PyCFunction)(void (*)(void))PulseWindow_extract, METH_FASTCALL,
     "extract(start_us, end_us, head, count) -> flags: PulseExtractor.extract over the bound ring (its head "
     "and count); amp, var into res, (flags, n_pulse, n_base, n_rec) into ires"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject PulseWindowType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.PulseWindow",
    .tp_basicsize = sizeof(PulseWindowObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "PulseWindow(t, b, flags, used_t, emp_var, res, ires, settle_us, fall_us, baseline_us, guard_us, "
              "min_pulse, min_base, max_gap_us, max_samples, drift_limit, sigma, drift_nsigma): a pulse "
              "extractor bound to its sample ring's arrays and its scratch",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)PulseWindow_init,
    .tp_dealloc = (destructor)PulseWindow_dealloc,
    .tp_methods = PulseWindow_methods,
};

/* ----------------------------------------------------------------- SolveIO */
#define SIO_NBUF 9
typedef struct {
    PyObject_HEAD
    int n;
    double *Sv, *wv, *cv, *m9, *p, *R, *rot, *pos, *st;
    double tol;
    Py_buffer views[SIO_NBUF];
    int bound;
} SolveIOObject;

static void SolveIO_dealloc(SolveIOObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < SIO_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int SolveIO_init(SolveIOObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "Sv", "wv", "cv", "m9", "p", "R", "rotation", "position", "st", "tol", NULL};
    static const char *names[SIO_NBUF] = {"Sv", "wv", "cv", "m9", "p", "R", "rotation", "position", "st"};
    PyObject *o[SIO_NBUF];
    double *ptr[SIO_NBUF];
    Py_ssize_t len[SIO_NBUF];
    double tol;
    int n, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOOOOOd", kwlist, &n, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                                     &o[6], &o[7], &o[8], &tol))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SolveIO: already bound");
        return -1;
    }
    if (n < 1 || n > 4096) {
        PyErr_Format(PyExc_ValueError, "SolveIO: n must be in 1..4096, got %d", n);
        return -1;
    }
    len[0] = len[1] = 3 * n;
    len[2] = n;
    len[3] = len[5] = len[6] = 9;
    len[4] = len[7] = 3;
    len[8] = 1;
    for (i = 0; i < SIO_NBUF; ++i) {
        if (ct_py_buffer(o[i], len[i], 8, "d", 1, &self->views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        ptr[i] = (double *)self->views[i].buf;
    }
    self->n = n;
    self->Sv = ptr[0];
    self->wv = ptr[1];
    self->cv = ptr[2];
    self->m9 = ptr[3];
    self->p = ptr[4];
    self->R = ptr[5];
    self->rot = ptr[6];
    self->pos = ptr[7];
    self->st = ptr[8];
    self->tol = tol;
    self->bound = 1;
    return 0;
}

/* load(S, sigma, cur) -> True, False or None: StagedSolve._load for float64 (3, n), (3, n), (n,)
 * buffers (None: another kind of input, for the Python's own checks); sigma_rms into st[0] */
static PyObject *SolveIO_load(SolveIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vs, vg, vc;
    int ok;
    if (!self->bound || nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "SolveIO.load(S, sigma, cur): bound, three arguments");
        return NULL;
    }
    if (!ct_py_view(args[0], &vs, 3, self->n))
        Py_RETURN_NONE;
    if (!ct_py_view(args[1], &vg, 3, self->n)) {
        PyBuffer_Release(&vs);
        Py_RETURN_NONE;
    }
    if (vs.strides[0] != vg.strides[0] || vs.strides[1] != vg.strides[1] || !ct_py_view(args[2], &vc, self->n, 0)) {
        PyBuffer_Release(&vs);
        PyBuffer_Release(&vg);
        Py_RETURN_NONE;
    }
    ok = ct_solve_load(self->n, (const double *)vs.buf, (const double *)vg.buf, vs.strides[0] / 8,
                       vs.strides[1] / 8, (const double *)vc.buf, vc.strides[0] / 8, self->Sv, self->wv, self->cv,
                       self->st);
    PyBuffer_Release(&vs);
    PyBuffer_Release(&vg);
    PyBuffer_Release(&vc);
    return PyBool_FromLong(ok);
}

/* x0(position, rotation) -> 0, 1, 2 or None: PoseSolver._load_x0 for float64 (3,), (3, 3) buffers:
 * 0 not finite; 1 the rotation copied into R, the position into p; 2 the same but the matrix is
 * no rotation (in m9: the caller projects it, linalg.nearest_rotation); None another kind of input */
static PyObject *SolveIO_x0(SolveIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vp, vr;
    double *m9 = self->m9, pp[3];
    int i, j, res = 1;
    if (!self->bound || nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "SolveIO.x0(position, rotation): bound, two arguments");
        return NULL;
    }
    if (!ct_py_view(args[0], &vp, 3, 0))
        Py_RETURN_NONE;
    if (!ct_py_view(args[1], &vr, 3, 3)) {
        PyBuffer_Release(&vp);
        Py_RETURN_NONE;
    }
    for (i = 0; i < 3 && res; ++i) {
        for (j = 0; j < 3; ++j) {
            m9[3 * i + j] = *(const double *)((const char *)vr.buf + i * vr.strides[0] + j * vr.strides[1]);
            if (!isfinite(m9[3 * i + j])) {
                res = 0;
                break;
            }
        }
        pp[i] = res ? *(const double *)((const char *)vp.buf + i * vp.strides[0]) : 0.0;
        if (res && !isfinite(pp[i]))
            res = 0;
    }
    PyBuffer_Release(&vp);
    PyBuffer_Release(&vr);
    if (!res)
        return PyLong_FromLong(0);
    self->p[0] = pp[0];
    self->p[1] = pp[1];
    self->p[2] = pp[2];
    if (!ct_is_rotation(m9, self->tol))
        return PyLong_FromLong(2);
    memcpy(self->R, m9, 9 * sizeof(double));
    return PyLong_FromLong(1);
}

/* publish() -> True or False: PoseSolver._publish's copies: the fit's R into m9 and, when it is a
 * rotation already, into rotation (False: the caller projects m9, linalg.nearest_rotation); the
 * fit's p into position */
static PyObject *SolveIO_publish(SolveIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->bound || nargs != 0) {
        PyErr_SetString(PyExc_TypeError, "SolveIO.publish(): bound, no argument");
        return NULL;
    }
    memcpy(self->m9, self->R, 9 * sizeof(double));
    memcpy(self->pos, self->p, 3 * sizeof(double));
    if (!ct_is_rotation(self->m9, self->tol))
        Py_RETURN_FALSE;
    memcpy(self->rot, self->m9, 9 * sizeof(double));
    Py_RETURN_TRUE;
}

static PyMethodDef SolveIO_methods[] = {
    {"load", (PyCFunction)(void (*)(void))SolveIO_load, METH_FASTCALL,
     "load(S, sigma, cur) -> True, False or None (StagedSolve._load)"},
    {"x0", (PyCFunction)(void (*)(void))SolveIO_x0, METH_FASTCALL,
     "x0(position, rotation) -> 0, 1, 2 or None (PoseSolver._load_x0)"},
    {"publish", (PyCFunction)(void (*)(void))SolveIO_publish, METH_FASTCALL,
     "publish() -> True or False (PoseSolver._publish's copies)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SolveIOType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SolveIO",
    .tp_basicsize = sizeof(SolveIOObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SolveIO(n, Sv, wv, cv, m9, p, R, rotation, position, st, tol): a pose solver's inputs and "
              "results bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SolveIO_init,
    .tp_dealloc = (destructor)SolveIO_dealloc,
    .tp_methods = SolveIO_methods,
};

int ct_py_pulse_window_of(PyObject *o, const struct ct_pulse **x, const struct ct_sample_ring **r, double **res,
                          int64_t **ires)
{
    PulseWindowObject *w = (PulseWindowObject *)o;
    if (!PyObject_TypeCheck(o, &PulseWindowType) || !w->bound) {
        PyErr_SetString(PyExc_TypeError, "needs a bound PulseWindow");
        return -1;
    }
    *x = &w->x;
    *r = &w->r;
    *res = w->res;
    *ires = w->ires;
    return 0;
}

int ct_register_window(PyObject *m)
{
    if (PyType_Ready(&PulseWindowType) < 0 || PyType_Ready(&SolveIOType) < 0)
        return -1;
    Py_INCREF(&PulseWindowType);
    if (PyModule_AddObject(m, "PulseWindow", (PyObject *)&PulseWindowType) < 0) {
        Py_DECREF(&PulseWindowType);
        return -1;
    }
    Py_INCREF(&SolveIOType);
    if (PyModule_AddObject(m, "SolveIO", (PyObject *)&SolveIOType) < 0) {
        Py_DECREF(&SolveIOType);
        return -1;
    }
    return 0;
}
