/*
 * CPython glue of a pose solve's warm path (src/solve.c): the type SolveRun, bound once (start-up)
 * to a PoseSolver's buffers (its fit's, its LM's, its results' and its state's); its per-call
 * methods (METH_FASTCALL) take the solve's input arrays and ints, write into the bound buffers and
 * create no Python object (the small ints they return are the interpreter's cached ones).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_solve.h"

/* the solver's caller-owned buffers: lengths in units of n (negative: a fixed count), writability */
#define SR_NBUF 24
static const char *sr_names[SR_NBUF] = {"geom", "B", "J", "S", "w", "cur", "h", "H", "p", "p_t", "R", "R_t",
                                        "A0", "g0", "A1", "g1", "d", "lmst", "cov", "rotation", "position", "m9",
                                        "work", "st"};
static const int sr_per_n[SR_NBUF] = {CT_COIL_STRIDE, 3, 9, 3, 3, 1, 3, 18, -3, -3, -9, -9, -36, -6, -36, -6, -6,
                                      -CT_LM_NST, -36, -9, -3, -9, -CT_ROBUST6_WORK, -CT_SV_NST};
static const int sr_ro[SR_NBUF] = {1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};

typedef struct {
    PyObject_HEAD
    struct ct_posefit f;
    struct ct_lm lm;
    struct ct_solve s;
    Py_buffer views[SR_NBUF];
    PyObject *acq;               /* the attached AcquireRun (s.acq its acquisition), or NULL */
    int bound;
} SolveRunObject;

static void SolveRun_dealloc(SolveRunObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < SR_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_XDECREF(self->acq);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int SolveRun_init(SolveRunObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "gate", "cx", "cy", "cz", "tol", "lam0", "lam_max", "iters", "cost_tol",
                             "step_sigma", "step_tol", "buffers", NULL};
    PyObject *bufs;
    double *ptr[SR_NBUF];
    Py_ssize_t len[SR_NBUF];
    double gate, cx, cy, cz, tol, lam0, lam_max, cost_tol, step_sigma, step_tol;
    int n, iters;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "idddddddidddO", kwlist, &n, &gate, &cx, &cy, &cz, &tol, &lam0,
                                     &lam_max, &iters, &cost_tol, &step_sigma, &step_tol, &bufs))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SolveRun: already bound");
        return -1;
    }
    if (n < 1 || n > 64) {
        PyErr_Format(PyExc_ValueError, "SolveRun: n must be in 1..64, got %d", n);
        return -1;
    }
    ct_py_lengths_per_n(sr_per_n, SR_NBUF, n, len);
    if (ct_py_float_buffers(bufs, SR_NBUF, len, sr_ro, sr_names, self->views, ptr, "SolveRun") < 0)
        return -1;
    self->f.n = n;
    self->f.geom = ptr[0];
    self->f.B = ptr[1];
    self->f.J = ptr[2];
    self->f.S = ptr[3];
    self->f.w = ptr[4];
    self->f.cur = ptr[5];
    self->f.h = ptr[6];
    self->f.H = ptr[7];
    self->f.p = ptr[8];
    self->f.p_t = ptr[9];
    self->f.R = ptr[10];
    self->f.R_t = ptr[11];
    self->f.step_tol = step_tol;
    self->lm.A[0] = ptr[12];
    self->lm.g[0] = ptr[13];
    self->lm.A[1] = ptr[14];
    self->lm.g[1] = ptr[15];
    self->lm.d = ptr[16];
    self->lm.st = ptr[17];
    self->lm.lam0 = lam0;
    self->lm.lam_max = lam_max;
    self->lm.iters = iters;
    self->lm.cost_tol = cost_tol;
    self->lm.step_sigma2 = step_sigma * step_sigma;
    self->s.f = &self->f;
    self->s.lm = &self->lm;
    self->s.n = n;
    self->s.gate = gate;
    self->s.cbar[0] = cx;
    self->s.cbar[1] = cy;
    self->s.cbar[2] = cz;
    self->s.tol = tol;
    self->s.cov = ptr[18];
    self->s.rot = ptr[19];
    self->s.pos = ptr[20];
    self->s.m9 = ptr[21];
    self->s.work = ptr[22];
    self->s.st = ptr[23];
    self->bound = 1;
    return 0;
}

/* the element (i, j) of a viewed matrix (j only for 2-D) */
static double sr_at(const Py_buffer *v, Py_ssize_t i, Py_ssize_t j)
{
    const char *b = (const char *)v->buf + i * v->strides[0];
    if (v->ndim == 2)
        b += j * v->strides[1];
    return *(const double *)b;
}

/* begin(S, sigma, cur, hemisphere, x0_position, x0_rotation) -> status (ct_solve_begin: 1 bad input,
 * 16 running, the phase in st) or None: an input of another kind (the caller's Python begin) */
static PyObject *SolveRun_begin(SolveRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer v[6];
    double hemi[3], x0p[3], x0R[9];
    const double *ph = NULL, *pp = NULL, *pr = NULL;
    int have[6] = {0, 0, 0, 0, 0, 0}, ok = 1, r = 0, i, j;
    const Py_ssize_t n = self->s.n;
    if (!self->bound || nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "SolveRun.begin(S, sigma, cur, hemisphere, x0_position, x0_rotation): "
                                         "bound, six arguments");
        return NULL;
    }
    if ((args[4] == Py_None) != (args[5] == Py_None))
        Py_RETURN_NONE;
    ok = (have[0] = ct_py_view(args[0], &v[0], 3, n)) && (have[1] = ct_py_view(args[1], &v[1], 3, n)) &&
         v[0].strides[0] == v[1].strides[0] && v[0].strides[1] == v[1].strides[1] &&
         (have[2] = ct_py_view(args[2], &v[2], n, 0)) &&
         (args[3] == Py_None || (have[3] = ct_py_view(args[3], &v[3], 3, 0))) &&
         (args[4] == Py_None ||
          ((have[4] = ct_py_view(args[4], &v[4], 3, 0)) && (have[5] = ct_py_view(args[5], &v[5], 3, 3))));
    if (ok) {
        if (have[3]) {
            for (i = 0; i < 3; ++i)
                hemi[i] = sr_at(&v[3], i, 0);
            ph = hemi;
        }
        if (have[4]) {
            for (i = 0; i < 3; ++i) {
                x0p[i] = sr_at(&v[4], i, 0);
                for (j = 0; j < 3; ++j)
                    x0R[3 * i + j] = sr_at(&v[5], i, j);
            }
            pp = x0p;
            pr = x0R;
        }
        r = ct_solve_begin(&self->s, (const double *)v[0].buf, (const double *)v[1].buf, v[0].strides[0] / 8,
                           v[0].strides[1] / 8, (const double *)v[2].buf, v[2].strides[0] / 8, ph, pp, pr);
    }
    for (i = 0; i < 6; ++i)
        if (have[i])
            PyBuffer_Release(&v[i]);
    if (!ok)
        Py_RETURN_NONE;
    return PyLong_FromLong(r);
}

/* run(spent, budget) -> phase (ct_solve_run); the units charged (spent included) into st[SPENT],
 * the evaluations done into st[EVALS] */
static PyObject *SolveRun_run(SolveRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t spent, budget;
    double *st = self->s.st, *lst = self->lm.st;
    int phase;
    if (!self->bound || nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "SolveRun.run(spent, budget): bound, two arguments");
        return NULL;
    }
    if (ct_py_int64(args[0], &spent) < 0 || ct_py_int64(args[1], &budget) < 0)
        return NULL;
    lst[CT_LM_EVALS] = 0.0;
    if (self->s.acq != NULL)
        self->s.acq->st[CT_AQ_EVALS] = 0.0;
    phase = ct_solve_run(&self->s, &spent, budget);
    st[CT_SV_SPENT] = (double)spent;
    st[CT_SV_EVALS] = lst[CT_LM_EVALS] + (self->s.acq != NULL ? self->s.acq->st[CT_AQ_EVALS] : 0.0);
    return PyLong_FromLong(phase);
}

/* predict(p, R, currents, out) -> True or None: StagedSolve.predict_signals, out[:, j] = R^T B_j(p)
 * (3, n) for the currents (n) through the bound model's geometry (ct_signal_fields without the
 * gradient, ct_signal_project); None: an array of another kind (the caller's Python) */
static PyObject *SolveRun_predict(SolveRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer v[4];
    double R[9], cur[64], h[3 * 64];
    const Py_ssize_t n = self->s.n;
    const struct ct_posefit *f = &self->f;
    int have[4] = {0, 0, 0, 0}, ok, i, j;
    if (!self->bound || nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "SolveRun.predict(p, R, currents, out): bound, four arguments");
        return NULL;
    }
    ok = (have[0] = ct_py_view(args[0], &v[0], 3, 0)) && (have[1] = ct_py_view(args[1], &v[1], 3, 3)) &&
         (have[2] = ct_py_view(args[2], &v[2], n, 0)) && (have[3] = ct_py_view(args[3], &v[3], 3, n)) && !v[3].readonly;
    if (ok) {
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j)
                R[3 * i + j] = sr_at(&v[1], i, j);
        for (j = 0; j < n; ++j)
            cur[j] = sr_at(&v[2], j, 0);
        ct_signal_fields(f->geom, (int)n, sr_at(&v[0], 0, 0), sr_at(&v[0], 1, 0), sr_at(&v[0], 2, 0), cur, 0, f->B,
                         f->J);
        ct_signal_project((int)n, R, f->B, h);
        for (j = 0; j < n; ++j)
            for (i = 0; i < 3; ++i)
                *(double *)((char *)v[3].buf + i * v[3].strides[0] + j * v[3].strides[1]) = h[3 * j + i];
    }
    for (i = 0; i < 4; ++i)
        if (have[i])
            PyBuffer_Release(&v[i]);
    if (!ok)
        Py_RETURN_NONE;
    Py_RETURN_TRUE;
}

/* attach(acq): the AcquireRun bound to this solver's buffers runs the acquisition inside run and
 * begin (ct_solve's acq; kept referenced); once, at start-up */
static PyObject *SolveRun_attach(SolveRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    const struct ct_acquire *a;
    if (!self->bound || nargs != 1 || self->acq != NULL) {
        PyErr_SetString(PyExc_TypeError, "SolveRun.attach(acq): bound, one argument, once");
        return NULL;
    }
    a = ct_py_acquire_of(args[0]);
    if (a == NULL)
        return NULL;
    if (a->n != self->s.n || a->S != self->f.S || a->cur != self->f.cur || a->geom != self->f.geom ||
        a->B != self->f.B || a->J != self->f.J) {
        PyErr_SetString(PyExc_ValueError, "SolveRun.attach: the acquisition is bound to other buffers");
        return NULL;
    }
    Py_INCREF(args[0]);
    self->acq = args[0];
    self->s.acq = a;
    Py_RETURN_NONE;
}

static PyMethodDef SolveRun_methods[] = {
    {"attach", (PyCFunction)(void (*)(void))SolveRun_attach, METH_FASTCALL,
     "attach(acq): run the acquisition (an AcquireRun on the same buffers) inside begin and run"},
    {"predict", (PyCFunction)(void (*)(void))SolveRun_predict, METH_FASTCALL,
     "predict(p, R, currents, out) -> True or None (StagedSolve.predict_signals; None: an array of another kind)"},
    {"begin", (PyCFunction)(void (*)(void))SolveRun_begin, METH_FASTCALL,
     "begin(S, sigma, cur, hemisphere, x0_position, x0_rotation) -> status or None (PoseSolver.begin's checks and "
     "copies; None: an input of another kind)"},
    {"run", (PyCFunction)(void (*)(void))SolveRun_run, METH_FASTCALL,
     "run(spent, budget) -> phase: the LM's start, steps and the finish while they fit (staged.run_units)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SolveRunType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SolveRun",
    .tp_basicsize = sizeof(SolveRunObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SolveRun(n, gate, cx, cy, cz, tol, lam0, lam_max, iters, cost_tol, step_sigma, step_tol, buffers): "
              "a pose solver's warm path (begin, the LM units and the finish) bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SolveRun_init,
    .tp_dealloc = (destructor)SolveRun_dealloc,
    .tp_methods = SolveRun_methods,
};

const struct ct_solve *ct_py_solve_of(PyObject *o)
{
    if (!PyObject_TypeCheck(o, &SolveRunType) || !((SolveRunObject *)o)->bound) {
        PyErr_SetString(PyExc_TypeError, "needs a bound SolveRun");
        return NULL;
    }
    return &((SolveRunObject *)o)->s;
}

int ct_register_solve(PyObject *m)
{
    if (PyType_Ready(&SolveRunType) < 0)
        return -1;
    Py_INCREF(&SolveRunType);
    if (PyModule_AddObject(m, "SolveRun", (PyObject *)&SolveRunType) < 0) {
        Py_DECREF(&SolveRunType);
        return -1;
    }
    if (PyModule_AddIntConstant(m, "SOLVE_NST", CT_SV_NST) < 0 || PyModule_AddIntConstant(m, "SOLVE_SPENT", CT_SV_SPENT) < 0
        || PyModule_AddIntConstant(m, "SOLVE_EVALS", CT_SV_EVALS) < 0)
        return -1;
    return 0;
}
