/*
 * CPython glue of a burst's opening for many sensors (src/burst_open.c): the type NewBursts binds
 * every sensor channel's done, flags and counters once (start-up) and its run() makes each
 * channel's new burst (measure.windows.ChannelBursts.new_burst); the type Schedules binds every
 * sensor's reference-instant array and its fusion snapshot's sq once and its run(t_ref) schedules
 * them all (track.burst_fusion.BurstFusionTracker.on_burst).  METH_FASTCALL; no Python object is
 * created per call.  The buffer tables are allocated once, at construction.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* the buffers bound: nv views, released at dealloc */
typedef struct {
    Py_buffer *views;
    Py_ssize_t nv;
} bo_views;

static void bo_release(bo_views *v)
{
    Py_ssize_t k;
    for (k = 0; k < v->nv; ++k)
        PyBuffer_Release(&v->views[k]);
    PyMem_Free(v->views);
    v->views = NULL;
    v->nv = 0;
}

/* a tuple of n items, or -1 with TypeError naming what */
static Py_ssize_t bo_tuple(PyObject *o, const char *what)
{
    if (!PyTuple_Check(o)) {
        PyErr_Format(PyExc_TypeError, "%s: needs a tuple of arrays", what);
        return -1;
    }
    return PyTuple_GET_SIZE(o);
}

/* bind item k of tuple t (n items of itemsize, formats, writable) as the next view; its buffer, or
 * NULL with the error set */
static void *bo_bind(bo_views *v, PyObject *t, Py_ssize_t k, Py_ssize_t n, Py_ssize_t itemsize, const char *formats,
                     const char *what)
{
    if (ct_py_buffer(PyTuple_GET_ITEM(t, k), n, itemsize, formats, 1, &v->views[v->nv], what) < 0)
        return NULL;
    return v->views[v->nv++].buf;
}

/* ------------------------------------------------------------- NewBursts */
typedef struct {
    PyObject_HEAD
    bo_views v;
    Py_ssize_t nch;
    int64_t ncoils;
    uint8_t **done;
    int64_t **flags, **cnt;
} NewBurstsObject;

static void NewBursts_dealloc(NewBurstsObject *self)
{
    bo_release(&self->v);
    PyMem_Free(self->done);
    PyMem_Free(self->flags);
    PyMem_Free(self->cnt);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int NewBursts_init(NewBurstsObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "done", "flags", "counts", NULL};
    PyObject *td, *tf, *tc;
    Py_ssize_t n, k;
    long long nc;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "LOOO", kwlist, &nc, &td, &tf, &tc))
        return -1;
    if (self->done != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "NewBursts: already bound");
        return -1;
    }
    n = bo_tuple(td, "NewBursts done");
    if (n < 0 || bo_tuple(tf, "NewBursts flags") < 0 || bo_tuple(tc, "NewBursts counts") < 0)
        return -1;
    if (nc < 1 || PyTuple_GET_SIZE(tf) != n || PyTuple_GET_SIZE(tc) != n) {
        PyErr_SetString(PyExc_ValueError, "NewBursts: n must be >= 1 and done, flags, counts one per channel");
        return -1;
    }
    self->v.views = PyMem_Calloc((size_t)(3 * n + 1), sizeof(Py_buffer));
    self->done = PyMem_Calloc((size_t)(n + 1), sizeof(uint8_t *));
    self->flags = PyMem_Calloc((size_t)(n + 1), sizeof(int64_t *));
    self->cnt = PyMem_Calloc((size_t)(n + 1), sizeof(int64_t *));
    if (!self->v.views || !self->done || !self->flags || !self->cnt) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        if (!(self->done[k] = bo_bind(&self->v, td, k, (Py_ssize_t)nc, 1, "?B", "NewBursts done")) ||
            !(self->flags[k] = bo_bind(&self->v, tf, k, (Py_ssize_t)nc, 8, "ql", "NewBursts flags")) ||
            !(self->cnt[k] = bo_bind(&self->v, tc, k, 2, 8, "ql", "NewBursts counts"))) {
            bo_release(&self->v);
            return -1;
        }
    }
    self->nch = n;
    self->ncoils = (int64_t)nc;
    return 0;
}

/* run(): every bound channel's new burst (ct_new_burst), in the channels' order */
static PyObject *NewBursts_run(NewBurstsObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_ssize_t k;
    (void)args;
    if (ct_py_nargs("run", nargs, 0) < 0)
        return NULL;
    if (self->v.views == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "NewBursts: not bound");
        return NULL;
    }
    for (k = 0; k < self->nch; ++k)
        ct_new_burst(self->ncoils, self->done[k], self->flags[k], self->cnt[k]);
    Py_RETURN_NONE;
}

static PyMethodDef NewBursts_methods[] = {
    {"run", (PyCFunction)(void (*)(void))NewBursts_run, METH_FASTCALL,
     "run(): each bound channel's new burst (measure.windows.SensorChannel.new_burst)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject NewBurstsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.NewBursts",
    .tp_basicsize = sizeof(NewBurstsObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "NewBursts(n, done, flags, counts): the sensor channels' done (bool, n), flags (int64, n) and counters "
              "(int64, 2: samples, changes), one tuple item per channel, bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)NewBursts_init,
    .tp_dealloc = (destructor)NewBursts_dealloc,
    .tp_methods = NewBursts_methods,
};

/* ------------------------------------------------------------- Schedules */
typedef struct {
    PyObject_HEAD
    bo_views v;
    Py_ssize_t n;
    int64_t **tr, **sq;
} SchedulesObject;

static void Schedules_dealloc(SchedulesObject *self)
{
    bo_release(&self->v);
    PyMem_Free(self->tr);
    PyMem_Free(self->sq);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Schedules_init(SchedulesObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"tr", "sq", NULL};
    PyObject *tt, *ts;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OO", kwlist, &tt, &ts))
        return -1;
    if (self->tr != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Schedules: already bound");
        return -1;
    }
    n = bo_tuple(tt, "Schedules tr");
    if (n < 0 || bo_tuple(ts, "Schedules sq") < 0)
        return -1;
    if (PyTuple_GET_SIZE(ts) != n) {
        PyErr_SetString(PyExc_ValueError, "Schedules: tr and sq one per sensor");
        return -1;
    }
    self->v.views = PyMem_Calloc((size_t)(2 * n + 1), sizeof(Py_buffer));
    self->tr = PyMem_Calloc((size_t)(n + 1), sizeof(int64_t *));
    self->sq = PyMem_Calloc((size_t)(n + 1), sizeof(int64_t *));
    if (!self->v.views || !self->tr || !self->sq) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        if (!(self->tr[k] = bo_bind(&self->v, tt, k, 1, 8, "ql", "Schedules tr")) ||
            !(self->sq[k] = bo_bind(&self->v, ts, k, 3, 8, "ql", "Schedules sq"))) {
            bo_release(&self->v);
            return -1;
        }
    }
    self->n = n;
    return 0;
}

/* run(t_ref): every bound sensor scheduled at t_ref (ct_schedule), in the sensors' order */
static PyObject *Schedules_run(SchedulesObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t;
    Py_ssize_t k;
    if (ct_py_nargs("run", nargs, 1) < 0 || ct_py_int64(args[0], &t) < 0)
        return NULL;
    if (self->v.views == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Schedules: not bound");
        return NULL;
    }
    for (k = 0; k < self->n; ++k)
        ct_schedule(self->tr[k], self->sq[k], t);
    Py_RETURN_NONE;
}

static PyMethodDef Schedules_methods[] = {
    {"run", (PyCFunction)(void (*)(void))Schedules_run, METH_FASTCALL,
     "run(t_ref): each bound sensor's reference instant and snapshot scheduled at t_ref "
     "(track.burst_fusion.SensorInertial.schedule)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject SchedulesType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Schedules",
    .tp_basicsize = sizeof(SchedulesObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Schedules(tr, sq): each sensor's reference instant (int64, 1) and its fusion snapshot's sq (int64, at least 3: "
              "t, pending, valid first), one tuple item per sensor, bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Schedules_init,
    .tp_dealloc = (destructor)Schedules_dealloc,
    .tp_methods = Schedules_methods,
};

int ct_register_burst_open(PyObject *m)
{
    return ct_py_add_type(m, &NewBurstsType, "NewBursts") < 0 || ct_py_add_type(m, &SchedulesType, "Schedules") < 0 ? -1 : 0;
}
