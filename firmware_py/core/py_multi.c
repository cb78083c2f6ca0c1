/*
 * CPython glue of the many-sensor kernels (src/multi.c): window_frame (one PULSE_WINDOW frame, as
 * Transmitter.pulse_window sends it) and sigma_from (SensorChannel.sigma_from).  METH_FASTCALL;
 * they read their arguments in place and create no Python object but window_frame's bytes.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"

/* an integer argument into *x; 0 (the error cleared) for anything struct.pack would refuse */
static int mul_int64(PyObject *o, int64_t *x)
{
    int overflow = 0;
    long long v = PyLong_AsLongLongAndOverflow(o, &overflow);
    if ((v == -1 && PyErr_Occurred()) || overflow) {
        PyErr_Clear();
        return 0;
    }
    *x = (int64_t)v;
    return 1;
}

/* an unsigned 64-bit argument ('Q') into *x; 0 (the error cleared) when struct.pack would refuse it */
static int mul_uint64(PyObject *o, uint64_t *x)
{
    unsigned long long v;
    PyObject *i = PyLong_Check(o) ? (Py_INCREF(o), o) : PyNumber_Index(o);
    if (i == NULL) {
        PyErr_Clear();
        return 0;
    }
    v = PyLong_AsUnsignedLongLong(i);
    Py_DECREF(i);
    if (v == (unsigned long long)-1 && PyErr_Occurred()) {
        PyErr_Clear();
        return 0;
    }
    *x = (uint64_t)v;
    return 1;
}

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
    if (!mul_int64(args[0], &seq) || !mul_int64(args[1], &src)) {
        PyErr_SetString(PyExc_TypeError, "window_frame: seq and src must be integers");
        return NULL;
    }
    for (k = 0; k < 6; ++k)
        if (!mul_int64(args[at[k]], &f[k]))
            Py_RETURN_NONE;
    if (!mul_uint64(args[5], &first) || !mul_uint64(args[6], &last))
        Py_RETURN_NONE;
    k = ct_window_frame(out, (int)(seq & 0xFF), (int)(src & 0xFF), f[0], f[1], f[2], first, last, f[3], f[4], f[5]);
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

static PyMethodDef multi_functions[] = {
    {"window_frame", (PyCFunction)(void (*)(void))mul_window_frame, METH_FASTCALL,
     "window_frame(seq, src, node, coil, pulse_id, first_us, last_us, n_used, n_base, flags) -> bytes or None: "
     "one PULSE_WINDOW frame as encode_frame makes it (None: a value the wire format refuses)"},
    {"sigma_from", (PyCFunction)(void (*)(void))mul_sigma_from, METH_FASTCALL,
     "sigma_from(var, sig, floor): sig = sqrt(max(var, floor)) item by item (SensorChannel.sigma_from)"},
    {NULL, NULL, 0, NULL}};

int ct_register_multi(PyObject *m)
{
    if (PyModule_AddFunctions(m, multi_functions) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "WINDOW_ID", CT_WINDOW_ID) < 0 ||
        PyModule_AddIntConstant(m, "WINDOW_PAYLOAD", CT_WINDOW_PAYLOAD) < 0 ||
        PyModule_AddIntConstant(m, "WINDOW_CRC_EXTRA", CT_WINDOW_CRC_EXTRA) < 0)
        return -1;
    return 0;
}
