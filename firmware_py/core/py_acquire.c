/*
 * CPython glue of a pose solve's acquisition (src/acquire.c): the type AcquireRun, bound once
 * (start-up) to a PoseSolver's buffers (its signal model's, its fit's signals and currents, the
 * grid, the start, the scratch and the state); attached to the solver's SolveRun (SolveRun.attach)
 * its units run inside SolveRun.run.  begin and unit (METH_FASTCALL) create no Python object.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_solve.h"

/* the acquisition's caller-owned buffers: lengths in units of n (negative: a fixed count) */
#define AQ_NBUF 10
static const char *aq_names[AQ_NBUF] = {"geom", "B", "J", "S", "cur", "grid", "p", "R", "work", "st"};
static const int aq_per_n[AQ_NBUF] = {CT_COIL_STRIDE, 3, 9, 3, 1, -3 * CT_AQ_GRID_DIRECTIONS, -3, -9, 0,
                                      -CT_AQ_NST};
static const int aq_ro[AQ_NBUF] = {1, 0, 0, 1, 1, 1, 0, 0, 0, 0};

typedef struct {
    PyObject_HEAD
    struct ct_acquire a;
    struct ct_lm lm;
    Py_buffer views[AQ_NBUF];
    int bound;
} AcquireRunObject;

static void AcquireRun_dealloc(AcquireRunObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < AQ_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int AcquireRun_init(AcquireRunObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "cx", "cy", "cz", "near", "mu0_4pi", "tol", "buffers", NULL};
    PyObject *bufs;
    double *ptr[AQ_NBUF];
    Py_ssize_t len[AQ_NBUF];
    double cx, cy, cz, near, mu0_4pi, tol;
    int n;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iddddddO", kwlist, &n, &cx, &cy, &cz, &near, &mu0_4pi, &tol, &bufs))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "AcquireRun: already bound");
        return -1;
    }
    if (n < 1 || n > 64) {
        PyErr_Format(PyExc_ValueError, "AcquireRun: n must be in 1..64, got %d", n);
        return -1;
    }
    ct_py_lengths_per_n(aq_per_n, AQ_NBUF, n, len);
    len[8] = CT_AQ_WORK_FIXED + (Py_ssize_t)n * n + 3 * (Py_ssize_t)n;
    if (ct_py_float_buffers(bufs, AQ_NBUF, len, aq_ro, aq_names, self->views, ptr, "AcquireRun") < 0)
        return -1;
    self->a.n = n;
    self->a.geom = ptr[0];
    self->a.B = ptr[1];
    self->a.J = ptr[2];
    self->a.S = ptr[3];
    self->a.cur = ptr[4];
    self->a.grid = ptr[5];
    self->a.p = ptr[6];
    self->a.R = ptr[7];
    self->a.work = ptr[8];
    self->a.st = ptr[9];
    self->a.cbar[0] = cx;
    self->a.cbar[1] = cy;
    self->a.cbar[2] = cz;
    self->a.near = near;
    self->a.mu0_4pi = mu0_4pi;
    self->a.tol = tol;
    ct_acquire_bind(&self->a, &self->lm);
    self->bound = 1;
    return 0;
}

/* begin(hx, hy, hz, sigma_rms) -> None (ct_acquire_begin) */
static PyObject *AcquireRun_begin(AcquireRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[4];
    int i;
    if (!self->bound || nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "AcquireRun.begin(hx, hy, hz, sigma_rms): bound, four arguments");
        return NULL;
    }
    for (i = 0; i < 4; ++i)
        if (ct_py_double(args[i], &v[i]) < 0)
            return NULL;
    ct_acquire_begin(&self->a, v[0], v[1], v[2], v[3]);
    Py_RETURN_NONE;
}

/* unit() -> the unit after the one run (ct_acquire_unit; 0: finished) */
static PyObject *AcquireRun_unit(AcquireRunObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->bound || nargs != 0) {
        PyErr_SetString(PyExc_TypeError, "AcquireRun.unit(): bound, no argument");
        return NULL;
    }
    return PyLong_FromLong(ct_acquire_unit(&self->a));
}

static PyMethodDef AcquireRun_methods[] = {
    {"begin", (PyCFunction)(void (*)(void))AcquireRun_begin, METH_FASTCALL,
     "begin(hx, hy, hz, sigma_rms): Acquisition.begin"},
    {"unit", (PyCFunction)(void (*)(void))AcquireRun_unit, METH_FASTCALL,
     "unit() -> the next unit after running one (Acquisition.next_unit(); 0: finished)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject AcquireRunType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.AcquireRun",
    .tp_basicsize = sizeof(AcquireRunObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "AcquireRun(n, cx, cy, cz, near, mu0_4pi, tol, buffers): a pose solver's acquisition (pose.acquire) "
              "bound to its buffers (geom, B, J, S, cur, grid, p, R, work, st)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)AcquireRun_init,
    .tp_dealloc = (destructor)AcquireRun_dealloc,
    .tp_methods = AcquireRun_methods,
};

const struct ct_acquire *ct_py_acquire_of(PyObject *o)
{
    if (!PyObject_TypeCheck(o, &AcquireRunType) || !((AcquireRunObject *)o)->bound) {
        PyErr_SetString(PyExc_TypeError, "needs a bound AcquireRun");
        return NULL;
    }
    return &((AcquireRunObject *)o)->a;
}

int ct_register_acquire(PyObject *m)
{
    if (ct_py_add_type(m, &AcquireRunType, "AcquireRun") < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "ACQUIRE_NST", CT_AQ_NST) < 0 ||
        PyModule_AddIntConstant(m, "ACQUIRE_WORK_FIXED", CT_AQ_WORK_FIXED) < 0 ||
        PyModule_AddIntConstant(m, "ACQUIRE_EVALS", CT_AQ_EVALS) < 0 ||
        PyModule_AddIntConstant(m, "ACQUIRE_OK", CT_AQ_OK) < 0 ||
        PyModule_AddIntConstant(m, "ACQUIRE_UNIT", CT_AQ_UNIT) < 0)
        return -1;
    return 0;
}
