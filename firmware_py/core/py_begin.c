/*
 * CPython glue of a burst's solve inputs at its begin (src/begin.c): the type BurstInputs, bound once
 * (start-up) to a tracker's channels' window flags, the schedule's faults and measured currents, the
 * nominal currents and the tracker's currents; its per-call methods (METH_FASTCALL) create no Python
 * object beyond the int they return.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

#define BI_MAXCH 64

typedef struct {
    PyObject_HEAD
    struct ct_begin_bits b;
    int nch, nf, nc;
    const int64_t *fl[BI_MAXCH];
    const int64_t *fv;
    const double *measured, *nominal;
    double *cur;
    Py_buffer views[BI_MAXCH + 4];
    int nviews;
} BurstInputsObject;

static void BurstInputs_dealloc(BurstInputsObject *self)
{
    int i;
    for (i = 0; i < self->nviews; ++i)
        PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* BurstInputs(flags, faults, measured, nominal, currents, bits): flags a sequence of the channels'
 * int64 window flags (n each), faults int64 (n), the float64 measured, nominal and currents (n); bits
 * the six masks of struct ct_begin_bits */
static int BurstInputs_init(BurstInputsObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"flags", "faults", "measured", "nominal", "currents", "bits", NULL};
    PyObject *flags, *faults, *measured, *nominal, *currents, *seq;
    long long m[6];
    Py_ssize_t nch, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOO(LLLLLL)", kwlist, &flags, &faults, &measured, &nominal,
                                     &currents, &m[0], &m[1], &m[2], &m[3], &m[4], &m[5]))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "BurstInputs: already bound");
        return -1;
    }
    seq = PySequence_Fast(flags, "BurstInputs: flags must be a sequence");
    if (seq == NULL)
        return -1;
    nch = PySequence_Fast_GET_SIZE(seq);
    if (nch < 1 || nch > BI_MAXCH) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "BurstInputs: 1..%d channels", BI_MAXCH);
        return -1;
    }
    if (ct_py_buffer(faults, 1, 8, "ql", 0, &self->views[0], "faults") < 0)
        goto fail;
    self->nviews = 1;
    self->nc = (int)(self->views[0].len / 8);
    if (ct_py_buffer(measured, self->nc, 8, "d", 0, &self->views[1], "measured") < 0)
        goto fail;
    self->nviews = 2;
    if (ct_py_buffer(nominal, self->nc, 8, "d", 0, &self->views[2], "nominal") < 0)
        goto fail;
    self->nviews = 3;
    if (ct_py_buffer(currents, self->nc, 8, "d", 1, &self->views[3], "currents") < 0)
        goto fail;
    self->nviews = 4;
    for (i = 0; i < nch; ++i) {
        Py_buffer *v = &self->views[4 + i];
        if (ct_py_buffer(PySequence_Fast_GET_ITEM(seq, i), 1, 8, "ql", 0, v, "flags") < 0)
            goto fail;
        self->nviews = 5 + (int)i;
        if (i == 0)
            self->nf = (int)(v->len / 8);
        else if (v->len / 8 != self->nf) {
            PyErr_SetString(PyExc_ValueError, "BurstInputs: the channels' flags differ in length");
            goto fail;
        }
        self->fl[i] = v->buf;
    }
    Py_DECREF(seq);
    self->nch = (int)nch;
    self->fv = self->views[0].buf;
    self->measured = self->views[1].buf;
    self->nominal = self->views[2].buf;
    self->cur = self->views[3].buf;
    self->b.pulse_saturated = m[0];
    self->b.pulse_unusable = m[1];
    self->b.coil_fatal = m[2];
    self->b.pose_saturated = m[3];
    self->b.pose_degraded = m[4];
    self->b.pose_coil_fault = m[5];
    return 0;
fail:
    Py_DECREF(seq);
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    return -1;
}

/* status(k) -> bits | unusable << 8 | flags << 9 for channel k (ct_begin_inputs) */
static PyObject *BurstInputs_status(BurstInputsObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k, flags;
    int unusable;
    int64_t bits;
    if (!self->nch || ct_py_nargs("status", nargs, 1) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    if (k < 0 || k >= self->nch) {
        PyErr_SetString(PyExc_IndexError, "BurstInputs.status: channel out of range");
        return NULL;
    }
    bits = ct_begin_inputs(&self->b, self->fl[k], self->nf, self->fv, self->nc, &flags, &unusable);
    if (bits < 0 || bits > 255 || flags < 0) {
        PyErr_SetString(PyExc_ValueError, "BurstInputs.status: bits or flags out of range");
        return NULL;
    }
    return PyLong_FromLongLong((long long)bits | ((long long)unusable << 8) | ((long long)flags << 9));
}

/* currents(): the tracker's currents from the driver's measured ones or the nominal (ct_prepare_currents) */
static PyObject *BurstInputs_currents(BurstInputsObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (!self->nch || ct_py_nargs("currents", nargs, 0) < 0)
        return NULL;
    ct_prepare_currents(self->measured, self->nominal, self->cur, self->nc);
    Py_RETURN_NONE;
}

static PyMethodDef BurstInputs_methods[] = {
    {"status", (PyCFunction)(void (*)(void))BurstInputs_status, METH_FASTCALL,
     "status(k) -> bits | unusable << 8 | flags << 9: channel k's burst flags, the faults, input_status"},
    {"currents", (PyCFunction)(void (*)(void))BurstInputs_currents, METH_FASTCALL,
     "currents(): MagneticTracker._prepare_currents into the bound currents"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject BurstInputsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.BurstInputs",
    .tp_basicsize = sizeof(BurstInputsObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "BurstInputs(flags, faults, measured, nominal, currents, bits): a tracker's burst inputs at a "
              "solve's begin bound to its channels' flags and the schedule's arrays",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)BurstInputs_init,
    .tp_dealloc = (destructor)BurstInputs_dealloc,
    .tp_methods = BurstInputs_methods,
};

int ct_register_begin(PyObject *m)
{
    return ct_py_add_type(m, &BurstInputsType, "BurstInputs");
}
