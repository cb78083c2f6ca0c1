/*
 * CPython glue of the supervisor's kernels (src/supervise.c): the type SupMag binds the supervisor's
 * two state arrays and the pulse schedule's start and end once (start-up); mag(node, t_us, x, y, z,
 * flip, now_us), reply(offset, now_us) and pose_status(node, window_flags) are METH_FASTCALL, read
 * their integers in place and return an int (mag, reply: a small one, no Python object created).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

enum { SUP_SI, SUP_SD, SUP_PS, SUP_PE, SUP_PAY, SUP_NVIEWS };

typedef struct {
    PyObject_HEAD
    Py_buffer views[SUP_NVIEWS];
    int nbound;
    int bound;                      /* si, sd, start, end bound (the payloads: optional) */
    Py_ssize_t pay_len;             /* 0: no payloads bound */
    struct ct_sup s;
} SupMagObject;

static void SupMag_dealloc(SupMagObject *self)
{
    int k;
    for (k = 0; k < self->nbound; ++k)
        PyBuffer_Release(&self->views[k]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int SupMag_init(SupMagObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"si", "sd", "start", "end", "payloads", NULL};
    PyObject *o[SUP_NVIEWS];
    int64_t n, nc;
    o[SUP_PAY] = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOO|O", kwlist, &o[SUP_SI], &o[SUP_SD], &o[SUP_PS], &o[SUP_PE],
                                     &o[SUP_PAY]))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "SupMag: already bound");
        return -1;
    }
    if (ct_py_buffer(o[SUP_SI], CT_SUP_NI, 8, "ql", 1, &self->views[SUP_SI], "SupMag si") < 0)
        return -1;
    self->nbound = 1;
    n = ((int64_t *)self->views[SUP_SI].buf)[CT_SUP_N];
    nc = ((int64_t *)self->views[SUP_SI].buf)[CT_SUP_NCOILS];
    if (n < 1 || n > CT_SUP_SLOTS || nc < 1 || self->views[SUP_SI].len < (Py_ssize_t)CT_SUP_SI_LEN(n, nc) * 8) {
        PyErr_SetString(PyExc_ValueError, "SupMag: si's node count, coil count or length is wrong");
        return -1;
    }
    if (ct_py_buffer(o[SUP_SD], CT_SUP_SD_LEN(n), 8, "d", 1, &self->views[SUP_SD], "SupMag sd") < 0)
        return -1;
    self->nbound = 2;
    if (ct_py_buffer(o[SUP_PS], nc, 8, "ql", 0, &self->views[SUP_PS], "SupMag start") < 0)
        return -1;
    self->nbound = 3;
    if (ct_py_buffer(o[SUP_PE], nc, 8, "ql", 0, &self->views[SUP_PE], "SupMag end") < 0)
        return -1;
    self->nbound = 4;
    if (o[SUP_PAY] != Py_None) {
        if (ct_py_buffer(o[SUP_PAY], 1, 1, "Bbc", 0, &self->views[SUP_PAY], "SupMag payloads") < 0)
            return -1;
        self->nbound = 5;
        self->pay_len = self->views[SUP_PAY].len;
    }
    self->bound = 1;
    ct_sup_bind(&self->s, (int64_t *)self->views[SUP_SI].buf, (double *)self->views[SUP_SD].buf,
                (const int64_t *)self->views[SUP_PS].buf, (const int64_t *)self->views[SUP_PE].buf);
    return 0;
}

static PyObject *SupMag_mag(SupMagObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[7];
    int k;
    if (nargs != 7) {
        PyErr_Format(PyExc_TypeError, "mag() takes 7 arguments (%zd given)", nargs);
        return NULL;
    }
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SupMag: not bound");
        return NULL;
    }
    for (k = 0; k < 7; ++k)
        if (ct_py_int64(args[k], &v[k]) < 0)
            return NULL;
    return PyLong_FromLong(ct_sup_mag(&self->s, v[0], v[1], v[2], v[3], v[4], v[5], v[6]));
}

static PyTypeObject SupMagType;

const struct ct_sup *ct_py_sup_of(PyObject *o)
{
    if (!PyObject_TypeCheck(o, &SupMagType) || !((SupMagObject *)o)->bound) {
        PyErr_SetString(PyExc_TypeError, "a bound SupMag is needed");
        return NULL;
    }
    return &((SupMagObject *)o)->s;
}

static PyObject *SupMag_pose_status(SupMagObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t node, flags;
    if (ct_py_nargs("pose_status", nargs, 2) < 0)
        return NULL;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SupMag: not bound");
        return NULL;
    }
    if (ct_py_int64(args[0], &node) < 0 || ct_py_int64(args[1], &flags) < 0)
        return NULL;
    return PyLong_FromLongLong(ct_sup_pose_status(&self->s, node, flags));
}

/* reply(offset, now_us) -> 0 or 1: the TIME_SYNC_REPLY whose payload starts at payloads[offset] */
static PyObject *SupMag_reply(SupMagObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t off, now;
    if (ct_py_nargs("reply", nargs, 2) < 0)
        return NULL;
    if (!self->bound || self->pay_len == 0) {
        PyErr_SetString(PyExc_RuntimeError, "SupMag: no payloads bound");
        return NULL;
    }
    if (ct_py_int64(args[0], &off) < 0 || ct_py_int64(args[1], &now) < 0)
        return NULL;
    if (off < 0 || off + 19 > self->pay_len) {
        PyErr_SetString(PyExc_ValueError, "reply: the payload lies outside the bound payloads");
        return NULL;
    }
    return PyLong_FromLong(ct_sup_reply(&self->s, (const uint8_t *)self->views[SUP_PAY].buf + off, now));
}

static PyMethodDef SupMag_methods[] = {
    {"reply", (PyCFunction)(void (*)(void))SupMag_reply, METH_FASTCALL,
     "reply(offset, now_us) -> 0 or 1: Supervisor.on_message for the TIME_SYNC_REPLY at payloads[offset] (0: done; "
     "1: a rare case for the Python reference, nothing changed)"},
    {"pose_status", (PyCFunction)(void (*)(void))SupMag_pose_status, METH_FASTCALL,
     "pose_status(node, window_flags) -> bits | veto << 32: Supervisor.pose_status's POSE_* bits and veto"},
    {"mag", (PyCFunction)(void (*)(void))SupMag_mag, METH_FASTCALL,
     "mag(node, t_us, x, y, z, flip, now_us) -> 0 or 1: Supervisor.on_message for a MAG_SAMPLE (0: done; 1: a rare "
     "case for the Python reference, nothing changed)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SupMagType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SupMag",
    .tp_basicsize = sizeof(SupMagObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SupMag(si, sd, start, end, payloads=None): the supervisor's state (two arrays, ct_supervise.h), the "
              "pulse schedule's start and end and the frame decoder's payloads, bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SupMag_init,
    .tp_dealloc = (destructor)SupMag_dealloc,
    .tp_methods = SupMag_methods,
};

int ct_register_supervise(PyObject *m)
{
    if (PyType_Ready(&SupMagType) < 0)
        return -1;
    Py_INCREF(&SupMagType);
    if (PyModule_AddObject(m, "SupMag", (PyObject *)&SupMagType) < 0) {
        Py_DECREF(&SupMagType);
        return -1;
    }
    if (PyModule_AddIntConstant(m, "SUP_NI", CT_SUP_NI) < 0 || PyModule_AddIntConstant(m, "SUP_ND", CT_SUP_ND) < 0 ||
        PyModule_AddIntConstant(m, "SUP_SLOTS", CT_SUP_SLOTS) < 0 ||
        PyModule_AddIntConstant(m, "SUP_SUSPECT", CT_SUP_SUSPECT) < 0 ||
        PyModule_AddIntConstant(m, "SUP_HISTORY", CT_SUP_HISTORY) < 0 ||
        PyModule_AddIntConstant(m, "SUP_REPLIES", CT_SUP_REPLIES) < 0 ||
        PyModule_AddIntConstant(m, "SUP_ACQUIRE", CT_SUP_ACQUIRE) < 0)
        return -1;
    return 0;
}
