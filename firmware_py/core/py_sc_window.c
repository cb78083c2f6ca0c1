/*
 * CPython glue of the single-coil window close's shared baselines (src/sc_window.c): the type
 * SharedBaselinesCore binds a SharedBaselines' state (its integers and floats, two arrays) and
 * its variance buffer once at construction, and with bind_channels the sensor channels' last
 * window (amp_var (3,) float64, info (4,) int64 each); close and variance are METH_FASTCALL, read
 * their integers in place and return None (no Python object created).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* the most sensor channels bind_channels takes */
#define SB_MAXCH 64

typedef struct {
    PyObject_HEAD
    int64_t *si;
    double *sf, *var;
    const double *amp_var[SB_MAXCH];
    const int64_t *info[SB_MAXCH];
    Py_buffer views[3 + 2 * SB_MAXCH];
    int nviews, nch;
} SbObject;

static void Sb_release(SbObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    self->nch = 0;
}

static void Sb_dealloc(SbObject *self)
{
    Sb_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* SharedBaselinesCore(si, sf, var): si int64 (CT_SB_NI), sf float64 (CT_SB_NF), var float64 (3) */
static int Sb_init(SbObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"si", "sf", "var", NULL};
    PyObject *si, *sf, *var;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOO", kwlist, &si, &sf, &var))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SharedBaselinesCore: already bound");
        return -1;
    }
    if (ct_py_buffer(si, CT_SB_NI, 8, "ql", 1, &self->views[0], "si") < 0)
        return -1;
    self->nviews = 1;
    if (ct_py_buffer(sf, CT_SB_NF, 8, "d", 1, &self->views[1], "sf") < 0) {
        Sb_release(self);
        return -1;
    }
    self->nviews = 2;
    if (ct_py_buffer(var, 3, 8, "d", 1, &self->views[2], "var") < 0) {
        Sb_release(self);
        return -1;
    }
    self->nviews = 3;
    self->si = (int64_t *)self->views[0].buf;
    self->sf = (double *)self->views[1].buf;
    self->var = (double *)self->views[2].buf;
    return 0;
}

static int Sb_ready(SbObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (self->nviews < 3) {
        PyErr_SetString(PyExc_RuntimeError, "SharedBaselinesCore: not bound");
        return -1;
    }
    return ct_py_nargs(name, nargs, want);
}

/* bind_channels(channels): a tuple (amp_var_0, info_0, amp_var_1, info_1, ...), once */
static PyObject *Sb_bind_channels(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    PyObject *t;
    Py_ssize_t m, k;
    if (Sb_ready(self, "bind_channels", nargs, 1) < 0)
        return NULL;
    t = args[0];
    if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) % 2 != 0 || PyTuple_GET_SIZE(t) / 2 > SB_MAXCH) {
        PyErr_Format(PyExc_ValueError, "bind_channels: a tuple of (amp_var, info) pairs, at most %d", SB_MAXCH);
        return NULL;
    }
    if (self->nch || self->nviews > 3) {
        PyErr_SetString(PyExc_RuntimeError, "bind_channels: already bound");
        return NULL;
    }
    m = PyTuple_GET_SIZE(t) / 2;
    for (k = 0; k < m; ++k) {
        if (ct_py_buffer(PyTuple_GET_ITEM(t, 2 * k), 3, 8, "d", 0, &self->views[self->nviews], "amp_var") < 0)
            goto fail;
        self->amp_var[k] = (const double *)self->views[self->nviews++].buf;
        if (ct_py_buffer(PyTuple_GET_ITEM(t, 2 * k + 1), 4, 8, "ql", 0, &self->views[self->nviews], "info") < 0)
            goto fail;
        self->info[k] = (const int64_t *)self->views[self->nviews++].buf;
    }
    self->nch = (int)m;
    Py_RETURN_NONE;
fail:
    while (self->nviews > 3)
        PyBuffer_Release(&self->views[--self->nviews]);
    return NULL;
}

/* close(start, end, next_start, earliest_next_us) (SharedBaselines.close; shared into sf) */
static PyObject *Sb_close(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[4];
    int k;
    if (Sb_ready(self, "close", nargs, 4) < 0)
        return NULL;
    for (k = 0; k < 4; ++k)
        if (ct_py_int64(args[k], &v[k]) < 0)
            return NULL;
    ct_sb_close(self->si, self->sf, v[0], v[1], v[2], v[3]);
    Py_RETURN_NONE;
}

/* variance(k): channel k's bound amp_var and info (SharedBaselines.variance) into var */
static PyObject *Sb_variance(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    if (Sb_ready(self, "variance", nargs, 1) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    if (k < 0 || k >= self->nch) {
        PyErr_SetString(PyExc_IndexError, "variance: no such bound channel");
        return NULL;
    }
    ct_sb_variance(self->si, self->sf, self->amp_var[k], self->info[k], self->var);
    Py_RETURN_NONE;
}

/* variance_of(amp_var, info): the same on caller arrays (the tests; the reference's call) */
static PyObject *Sb_variance_of(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer a, i;
    if (Sb_ready(self, "variance_of", nargs, 2) < 0)
        return NULL;
    if (ct_py_buffer(args[0], 3, 8, "d", 0, &a, "amp_var") < 0)
        return NULL;
    if (ct_py_buffer(args[1], 4, 8, "ql", 0, &i, "info") < 0) {
        PyBuffer_Release(&a);
        return NULL;
    }
    ct_sb_variance(self->si, self->sf, (const double *)a.buf, (const int64_t *)i.buf, self->var);
    PyBuffer_Release(&a);
    PyBuffer_Release(&i);
    Py_RETURN_NONE;
}

static PyMethodDef Sb_methods[] = {
    {"bind_channels", (PyCFunction)(void (*)(void))Sb_bind_channels, METH_FASTCALL,
     "bind_channels((amp_var_0, info_0, ...)): the channels' last windows, bound once"},
    {"close", (PyCFunction)(void (*)(void))Sb_close, METH_FASTCALL,
     "close(start, end, next_start, earliest_next_us): SharedBaselines.close"},
    {"variance", (PyCFunction)(void (*)(void))Sb_variance, METH_FASTCALL,
     "variance(k): SharedBaselines.variance of bound channel k into var"},
    {"variance_of", (PyCFunction)(void (*)(void))Sb_variance_of, METH_FASTCALL,
     "variance_of(amp_var, info): SharedBaselines.variance into var"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SbType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SharedBaselinesCore",
    .tp_basicsize = sizeof(SbObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SharedBaselinesCore(si, sf, var): estimate.shared_baseline.SharedBaselines' close and variance "
              "bound to its state arrays",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Sb_init,
    .tp_dealloc = (destructor)Sb_dealloc,
    .tp_methods = Sb_methods,
};

int ct_register_sc_window(PyObject *m)
{
    if (PyType_Ready(&SbType) < 0)
        return -1;
    Py_INCREF(&SbType);
    if (PyModule_AddObject(m, "SharedBaselinesCore", (PyObject *)&SbType) < 0) {
        Py_DECREF(&SbType);
        return -1;
    }
    if (PyModule_AddIntConstant(m, "SB_NI", CT_SB_NI) < 0 || PyModule_AddIntConstant(m, "SB_NF", CT_SB_NF) < 0 ||
        PyModule_AddIntConstant(m, "SB_MAXCH", SB_MAXCH) < 0)
        return -1;
    return 0;
}
