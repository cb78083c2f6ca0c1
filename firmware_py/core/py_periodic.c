/*
 * CPython glue of the periodic frames (src/periodic.c): sync_frame (one TIME_SYNC, as
 * Transmitter.time_sync sends it), heartbeat_frame (one HEARTBEAT, as Transmitter.step) and
 * event_frame (one FAULT_EVENT, as Transmitter.event).  METH_FASTCALL; each reads its integer
 * arguments in place and creates no Python object but the frame's bytes (None: a value the wire
 * format refuses, as struct.pack's error, which the transmitter counts as a tx error).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* the frame's sequence number and source (integers, masked to a byte as encode_frame does) */
static int per_header(PyObject *const *args, const char *name, int *seq, int *src)
{
    int64_t a, b;
    if (!ct_py_pack_q(args[0], &a) || !ct_py_pack_q(args[1], &b)) {
        PyErr_Format(PyExc_TypeError, "%s: seq and src must be integers", name);
        return -1;
    }
    *seq = (int)(a & 0xFF);
    *src = (int)(b & 0xFF);
    return 0;
}

/* sync_frame(seq, src, master_time_us, sync_seq) -> bytes or None */
static PyObject *per_sync_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_SYNC_FRAME_MAX];
    int seq, src, k;
    uint64_t t;
    int64_t s;
    (void)mod;
    if (nargs != 4) {
        PyErr_Format(PyExc_TypeError, "sync_frame() takes 4 arguments (%zd given)", nargs);
        return NULL;
    }
    if (per_header(args, "sync_frame", &seq, &src) < 0)
        return NULL;
    if (!ct_py_pack_Q(args[2], &t) || !ct_py_pack_q(args[3], &s))
        Py_RETURN_NONE;
    k = ct_sync_frame(out, seq, src, t, s);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* heartbeat_frame(seq, src, node, role, state, proto_version, schema_hash, errors) -> bytes or None */
static PyObject *per_heartbeat_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_HEARTBEAT_FRAME_MAX];
    int seq, src, k, i;
    int64_t f[6];
    (void)mod;
    if (nargs != 8) {
        PyErr_Format(PyExc_TypeError, "heartbeat_frame() takes 8 arguments (%zd given)", nargs);
        return NULL;
    }
    if (per_header(args, "heartbeat_frame", &seq, &src) < 0)
        return NULL;
    for (i = 0; i < 6; ++i)
        if (!ct_py_pack_q(args[2 + i], &f[i]))
            Py_RETURN_NONE;
    k = ct_heartbeat_frame(out, seq, src, f[0], f[1], f[2], f[3], f[4], f[5]);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* event_frame(seq, src, node, t_us, code, detail) -> bytes or None */
static PyObject *per_event_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_EVENT_FRAME_MAX];
    int seq, src, k;
    int64_t node, code, detail;
    uint64_t t;
    (void)mod;
    if (nargs != 6) {
        PyErr_Format(PyExc_TypeError, "event_frame() takes 6 arguments (%zd given)", nargs);
        return NULL;
    }
    if (per_header(args, "event_frame", &seq, &src) < 0)
        return NULL;
    if (!ct_py_pack_q(args[2], &node) || !ct_py_pack_Q(args[3], &t) || !ct_py_pack_q(args[4], &code) ||
        !ct_py_pack_q(args[5], &detail))
        Py_RETURN_NONE;
    k = ct_event_frame(out, seq, src, node, t, code, detail);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

static PyMethodDef periodic_functions[] = {
    {"sync_frame", (PyCFunction)(void (*)(void))per_sync_frame, METH_FASTCALL,
     "sync_frame(seq, src, master_time_us, sync_seq) -> bytes or None: one TIME_SYNC frame as encode_frame makes "
     "it (None: a value the wire format refuses)"},
    {"heartbeat_frame", (PyCFunction)(void (*)(void))per_heartbeat_frame, METH_FASTCALL,
     "heartbeat_frame(seq, src, node, role, state, proto_version, schema_hash, errors) -> bytes or None: one "
     "HEARTBEAT frame as encode_frame makes it"},
    {"event_frame", (PyCFunction)(void (*)(void))per_event_frame, METH_FASTCALL,
     "event_frame(seq, src, node, t_us, code, detail) -> bytes or None: one FAULT_EVENT frame as encode_frame "
     "makes it"},
    {NULL, NULL, 0, NULL}};

int ct_register_periodic(PyObject *m)
{
    static const struct {
        const char *name;
        long v;
    } consts[] = {
        {"SYNC_ID", CT_SYNC_ID}, {"SYNC_PAYLOAD", CT_SYNC_PAYLOAD}, {"SYNC_CRC_EXTRA", CT_SYNC_CRC_EXTRA},
        {"HEARTBEAT_ID", CT_HEARTBEAT_ID}, {"HEARTBEAT_PAYLOAD", CT_HEARTBEAT_PAYLOAD},
        {"HEARTBEAT_CRC_EXTRA", CT_HEARTBEAT_CRC_EXTRA}, {"EVENT_ID", CT_EVENT_ID},
        {"EVENT_PAYLOAD", CT_EVENT_PAYLOAD}, {"EVENT_CRC_EXTRA", CT_EVENT_CRC_EXTRA},
    };
    size_t i;
    if (PyModule_AddFunctions(m, periodic_functions) < 0)
        return -1;
    for (i = 0; i < sizeof consts / sizeof consts[0]; ++i)
        if (PyModule_AddIntConstant(m, consts[i].name, consts[i].v) < 0)
            return -1;
    return 0;
}
