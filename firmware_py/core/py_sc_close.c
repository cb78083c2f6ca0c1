/*
 * CPython glue of the single-coil window close's health check (src/sc_close.c): the type SuspectSpan
 * binds the supervisor's state arrays (si int64, sd float64: ct_supervise.h's layout, the arrays
 * Health.use_arrays keeps its lists in) once at construction; either(node, other, t0, t1) is
 * METH_FASTCALL, reads its integers in place and returns a bool (no Python object created).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "coiltrack_core.h"
#include "py_glue.h"

typedef struct {
    PyObject_HEAD
    struct ct_sup s;
    Py_buffer views[2];
    int nviews;
} SuspectSpanObject;

static void SuspectSpan_release(SuspectSpanObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void SuspectSpan_dealloc(SuspectSpanObject *self)
{
    SuspectSpan_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* SuspectSpan(si, sd) */
static int SuspectSpan_init(SuspectSpanObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"si", "sd", NULL};
    PyObject *si, *sd;
    int64_t n, nc;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OO", kwlist, &si, &sd))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SuspectSpan: already bound");
        return -1;
    }
    if (ct_py_buffer(si, CT_SUP_NI, 8, "ql", 0, &self->views[0], "SuspectSpan si") < 0)
        return -1;
    self->nviews = 1;
    n = ((int64_t *)self->views[0].buf)[CT_SUP_N];
    nc = ((int64_t *)self->views[0].buf)[CT_SUP_NCOILS];
    if (n < 1 || n > CT_SUP_SLOTS || nc < 0 || self->views[0].len < (Py_ssize_t)CT_SUP_SI_LEN(n, nc) * 8) {
        SuspectSpan_release(self);
        PyErr_SetString(PyExc_ValueError, "SuspectSpan: si shorter than its nodes and coils need");
        return -1;
    }
    if (ct_py_buffer(sd, CT_SUP_SD_LEN(n), 8, "d", 0, &self->views[1], "SuspectSpan sd") < 0) {
        SuspectSpan_release(self);
        return -1;
    }
    self->nviews = 2;
    ct_sup_bind(&self->s, (int64_t *)self->views[0].buf, (double *)self->views[1].buf, NULL, NULL);
    return 0;
}

/* either(node, other, t0, t1) -> bool: Health.suspect(node, t0, t1) or Health.suspect(other, t0, t1) */
static PyObject *SuspectSpan_either(SuspectSpanObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[4];
    int k;
    if (self->nviews < 2) {
        PyErr_SetString(PyExc_RuntimeError, "SuspectSpan: not bound");
        return NULL;
    }
    if (ct_py_nargs("either", nargs, 4) < 0)
        return NULL;
    for (k = 0; k < 4; ++k)
        if (ct_py_int64(args[k], &v[k]) < 0)
            return NULL;
    if (ct_scc_suspect_either(&self->s, v[0], v[1], v[2], v[3]))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef SuspectSpan_methods[] = {
    {"either", (PyCFunction)(void (*)(void))SuspectSpan_either, METH_FASTCALL,
     "either(node, other, t0, t1) -> bool: Health.suspect_either (node's or other's clock suspect anywhere in "
     "[t0, t1])"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SuspectSpanType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SuspectSpan",
    .tp_basicsize = sizeof(SuspectSpanObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SuspectSpan(si, sd): the supervisor's state arrays (ct_supervise.h), bound once: Health.suspect "
              "of a sensor and the coil driver in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SuspectSpan_init,
    .tp_dealloc = (destructor)SuspectSpan_dealloc,
    .tp_methods = SuspectSpan_methods,
};

int ct_register_sc_close(PyObject *m)
{
    return ct_py_add_type(m, &SuspectSpanType, "SuspectSpan");
}
