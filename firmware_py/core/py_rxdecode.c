/*
 * The CPython glue of the receive stage's frame decode (src/rxdecode.c): RxDecode binds the
 * decoder's caller-owned buffers once (start-up); decode(data, pos, now_us) is METH_FASTCALL,
 * reads the bytes in place and writes rows into the bound table (it returns a small int).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* a C-contiguous buffer of at least n items of itemsize bytes (int64 'q'/'l' or bytes 'B'),
 * writable or not, or -1 with TypeError naming `what` */
static int rx_get(PyObject *obj, Py_ssize_t n, Py_ssize_t itemsize, int writable, Py_buffer *view,
                  const char *what)
{
    return ct_py_buffer(obj, n, itemsize, itemsize == 8 ? "ql" : "Bbc", writable, view, what);
}

enum { RX_SIZES, RX_EXTRAS, RX_ST, RX_SEQ, RX_ROWS, RX_PAY, RX_BUF, RX_RAW, RX_NVIEWS };

typedef struct {
    PyObject_HEAD
    Py_buffer views[RX_NVIEWS];
    int nbound;
    struct ct_rx d;
} RxDecodeObject;

/* A tick's data, read in place: a bytes object's own bytes, else its buffer (v, to be released:
 * returns 1); 0 for bytes, -1 with the exception set where obj has no buffer */
static int rx_data(PyObject *obj, const uint8_t **p, Py_ssize_t *n, Py_buffer *v)
{
    if (PyBytes_Check(obj)) {
        *p = (const uint8_t *)PyBytes_AS_STRING(obj);
        *n = PyBytes_GET_SIZE(obj);
        return 0;
    }
    if (PyObject_GetBuffer(obj, v, PyBUF_SIMPLE) < 0)
        return -1;
    *p = (const uint8_t *)v->buf;
    *n = v->len;
    return 1;
}

static void RxDecode_dealloc(RxDecodeObject *self)
{
    int k;
    for (k = 0; k < self->nbound; ++k)
        PyBuffer_Release(&self->views[k]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int RxDecode_init(RxDecodeObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"sizes", "extras", "st", "last_seq", "rows", "pay", "buf", "raw", "max_encoded",
                             "max_payload", NULL};
    PyObject *o[RX_NVIEWS];
    int max_encoded, max_payload, k;
    Py_ssize_t cap;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOOii", kwlist, &o[RX_SIZES], &o[RX_EXTRAS], &o[RX_ST],
                                     &o[RX_SEQ], &o[RX_ROWS], &o[RX_PAY], &o[RX_BUF], &o[RX_RAW], &max_encoded,
                                     &max_payload))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RxDecode: already bound");
        return -1;
    }
    if (max_encoded < 1 || max_payload < 1 || max_payload > 255) {
        PyErr_SetString(PyExc_ValueError, "RxDecode: max_encoded >= 1 and max_payload in 1..255");
        return -1;
    }
    {
        static const char *what[RX_NVIEWS] = {"sizes", "extras", "st", "last_seq", "rows", "pay", "buf", "raw"};
        const Py_ssize_t want[RX_NVIEWS] = {256, 256, CT_RX_NST, 256, CT_RXR_W, 0, max_encoded, max_encoded};
        for (k = 0; k < RX_NVIEWS; ++k) {
            int bytes = k == RX_PAY || k == RX_BUF || k == RX_RAW;
            if (rx_get(o[k], want[k], bytes ? 1 : 8, k >= RX_ST, &self->views[k], what[k]) < 0) {
                while (k-- > 0)
                    PyBuffer_Release(&self->views[k]);
                return -1;
            }
        }
    }
    cap = self->views[RX_ROWS].len / (8 * CT_RXR_W);
    if (self->views[RX_PAY].len < cap * max_payload || cap > 65536) {
        for (k = 0; k < RX_NVIEWS; ++k)
            PyBuffer_Release(&self->views[k]);
        PyErr_SetString(PyExc_ValueError, "RxDecode: pay needs max_payload bytes per row (at most 65536 rows)");
        return -1;
    }
    self->nbound = RX_NVIEWS;
    self->d.sizes = (const int64_t *)self->views[RX_SIZES].buf;
    self->d.extras = (const int64_t *)self->views[RX_EXTRAS].buf;
    self->d.st = (int64_t *)self->views[RX_ST].buf;
    self->d.last_seq = (int64_t *)self->views[RX_SEQ].buf;
    self->d.rows = (int64_t *)self->views[RX_ROWS].buf;
    self->d.pay = (uint8_t *)self->views[RX_PAY].buf;
    self->d.buf = (uint8_t *)self->views[RX_BUF].buf;
    self->d.raw = (uint8_t *)self->views[RX_RAW].buf;
    self->d.cap = (int)cap;
    self->d.max_encoded = max_encoded;
    self->d.max_payload = max_payload;
    for (k = 0; k < 256; ++k)
        if (self->d.sizes[k] > max_payload || self->d.extras[k] < 0 || self->d.extras[k] > 255) {
            for (k = 0; k < RX_NVIEWS; ++k)
                PyBuffer_Release(&self->views[k]);
            self->nbound = 0;
            PyErr_SetString(PyExc_ValueError, "RxDecode: a size beyond max_payload or an extra outside 0..255");
            return -1;
        }
    return 0;
}

/* decode(data, pos, now_us) -> rows: FrameDecoder.feed of data[pos:] (st[RX_POS]: where it stopped) */
static PyObject *RxDecode_decode(RxDecodeObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    const uint8_t *p;
    Py_ssize_t n;
    long long pos, now;
    Py_buffer v;
    int rows, view;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RxDecode: not bound");
        return NULL;
    }
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "decode() takes 3 arguments (%zd given)", nargs);
        return NULL;
    }
    if ((view = rx_data(args[0], &p, &n, &v)) < 0)
        return NULL;
    pos = PyLong_AsLongLong(args[1]);
    now = (pos == -1 && PyErr_Occurred()) ? -1 : PyLong_AsLongLong(args[2]);
    if ((pos == -1 || now == -1) && PyErr_Occurred()) {
        if (view)
            PyBuffer_Release(&v);
        return NULL;
    }
    if (pos < 0 || pos > n) {
        if (view)
            PyBuffer_Release(&v);
        PyErr_SetString(PyExc_ValueError, "decode: pos outside the data");
        return NULL;
    }
    rows = ct_rx_feed(&self->d, p, (int64_t)n, (int64_t)pos, (int64_t)now);
    if (view)
        PyBuffer_Release(&v);
    return PyLong_FromLong(rows);
}

static PyMethodDef RxDecode_methods[] = {
    {"decode", (PyCFunction)(void (*)(void))RxDecode_decode, METH_FASTCALL,
     "decode(data, pos, now_us) -> rows: protocol.framing.FrameDecoder.feed of data[pos:] into the bound rows"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RxDecodeType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.RxDecode",
    .tp_basicsize = sizeof(RxDecodeObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "RxDecode(sizes, extras, st, last_seq, rows, pay, buf, raw, max_encoded, max_payload): the "
              "receive stage's frame decoder bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RxDecode_init,
    .tp_dealloc = (destructor)RxDecode_dealloc,
    .tp_methods = RxDecode_methods,
};

/* ------------------------------------------------------------- RxRoute */
enum { RT_NODES, RT_ST, RT_NVIEWS };

typedef struct {
    PyObject_HEAD
    PyObject *held;                 /* (decoder, sup, pushes): what the pointers below point into */
    Py_buffer views[RT_NVIEWS];
    int nbound;
    struct ct_rx_chan ch[256];
    struct ct_rx_route r;
} RxRouteObject;

static void RxRoute_dealloc(RxRouteObject *self)
{
    int k;
    for (k = 0; k < self->nbound; ++k)
        PyBuffer_Release(&self->views[k]);
    Py_XDECREF(self->held);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int RxRoute_fail(RxRouteObject *self, PyObject *exc, const char *msg)
{
    int k;
    for (k = 0; k < self->nbound; ++k)
        PyBuffer_Release(&self->views[k]);
    self->nbound = 0;
    if (exc != NULL)
        PyErr_SetString(exc, msg);
    return -1;
}

static int RxRoute_init(RxRouteObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"decoder", "sup", "nodes", "pushes", "st", "lsb", "limit", NULL};
    PyObject *dec, *sup, *nodes, *pushes, *st;
    const int64_t *chan;
    double lsb;
    long long limit;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOdL", kwlist, &dec, &sup, &nodes, &pushes, &st, &lsb, &limit))
        return -1;
    if (self->held != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "RxRoute: already bound");
        return -1;
    }
    if (!PyObject_TypeCheck(dec, &RxDecodeType) || !((RxDecodeObject *)dec)->nbound) {
        PyErr_SetString(PyExc_TypeError, "RxRoute: decoder must be a bound RxDecode");
        return -1;
    }
    if (!PyTuple_Check(pushes) || (n = PyTuple_GET_SIZE(pushes)) > 256) {
        PyErr_SetString(PyExc_TypeError, "RxRoute: pushes must be a tuple of at most 256 SamplePush");
        return -1;
    }
    self->r.sup = NULL;
    if (sup != Py_None && (self->r.sup = ct_py_sup_of(sup)) == NULL)
        return -1;
    for (k = 0; k < n; ++k) {
        struct ct_rx_chan *c = &self->ch[k];
        if (ct_py_sample_push_of(PyTuple_GET_ITEM(pushes, k), &c->t, &c->b, &c->flags, &c->cap, &c->st, &c->cnt) < 0)
            return -1;
    }
    if (ct_py_buffer(nodes, 256, 8, "ql", 0, &self->views[RT_NODES], "RxRoute nodes") < 0)
        return -1;
    self->nbound = 1;
    if (ct_py_buffer(st, CT_RXS_N, 8, "ql", 1, &self->views[RT_ST], "RxRoute st") < 0)
        return RxRoute_fail(self, NULL, NULL);
    self->nbound = 2;
    chan = (const int64_t *)self->views[RT_NODES].buf;
    for (k = 0; k < 256; ++k)
        if (chan[k] < -1 || chan[k] >= n)
            return RxRoute_fail(self, PyExc_ValueError, "RxRoute: a node's channel outside -1..len(pushes)-1");
    self->held = PyTuple_Pack(3, dec, sup, pushes);
    if (self->held == NULL)
        return RxRoute_fail(self, NULL, NULL);
    self->r.d = &((RxDecodeObject *)dec)->d;
    self->r.chan = chan;
    self->r.ch = self->ch;
    self->r.st = (int64_t *)self->views[RT_ST].buf;
    self->r.lsb = lsb;
    self->r.limit = (int64_t)limit;
    return 0;
}

/* step(data, mode, now_us) -> row, -1 or -2: ct_rx_step (the data read in place, as decode reads it) */
static PyObject *RxRoute_step(RxRouteObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    const uint8_t *p;
    Py_ssize_t n;
    int64_t mode, now, row;
    const int64_t *s;
    Py_buffer v;
    int view;
    if (self->held == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "RxRoute: not bound");
        return NULL;
    }
    if (ct_py_nargs("step", nargs, 3) < 0 || ct_py_int64(args[1], &mode) < 0 || ct_py_int64(args[2], &now) < 0)
        return NULL;
    s = self->r.st;
    if (mode < CT_RX_NEW || mode > CT_RX_TAKEN) {
        PyErr_SetString(PyExc_ValueError, "step: mode is 0 (new data), 1 (resume) or 2 (data taken)");
        return NULL;
    }
    if (mode == CT_RX_RESUME &&
        !(0 <= s[CT_RXS_NEXT] && s[CT_RXS_NEXT] <= s[CT_RXS_ROWS] && s[CT_RXS_ROWS] <= self->r.d->cap)) {
        PyErr_SetString(PyExc_ValueError, "step: the route's rows outside the table");
        return NULL;
    }
    if ((view = rx_data(args[0], &p, &n, &v)) < 0)
        return NULL;
    row = ct_rx_step(&self->r, p, (int64_t)n, (int)mode, now);
    if (view)
        PyBuffer_Release(&v);
    return PyLong_FromLongLong(row);
}

static PyMethodDef RxRoute_methods[] = {
    {"step", (PyCFunction)(void (*)(void))RxRoute_step, METH_FASTCALL,
     "step(data, mode, now_us) -> row, -1 or -2: Receiver._step_rows's decode and routing of data's magnetometer "
     "rows (into the supervisor and the bound channels) up to the next row the caller routes (its index in the "
     "decoder's rows), -1 when all are routed; mode 0 new data (-2: it holds the frame limit or more, nothing "
     "done), 1 go on after the row handed back, 2 new data already cut to the limit"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RxRouteType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.RxRoute",
    .tp_basicsize = sizeof(RxRouteObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "RxRoute(decoder, sup, nodes, pushes, st, lsb, limit): the receive stage's frame decoder (RxDecode), the "
              "supervisor's SupMag (or None), node -> channel index (int64, 256, -1: none), the channels' SamplePush "
              "(tuple), its state (int64, RXS_N), MAG_LSB_T and the frames a tick routes at most (0: all), bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RxRoute_init,
    .tp_dealloc = (destructor)RxRoute_dealloc,
    .tp_methods = RxRoute_methods,
};

int ct_register_rxdecode(PyObject *m)
{
    static const struct { const char *name; long value; } ints[] = {
        {"RX_NST", CT_RX_NST}, {"RX_POS", CT_RX_POS}, {"RX_BUFLEN", CT_RX_BUFLEN}, {"RX_DROPPING", CT_RX_DROPPING},
        {"RXR_W", CT_RXR_W}, {"RXR_KIND", CT_RXR_KIND}, {"RXR_CLIP", CT_RXR_CLIP}, {"RXR_STAMP", CT_RXR_STAMP},
        {"RXK_RAW", CT_RXK_RAW}, {"RXK_MAG_PACKED", CT_RXK_MAG_PACKED}, {"RXK_MAG", CT_RXK_MAG},
        {"RXK_IMU", CT_RXK_IMU}, {"STAMP_FLIP", CT_STAMP_FLIP}, {"RXS_N", CT_RXS_N},
        {"RXS_PACKED", CT_RXS_PACKED}, {"RX_NEW", CT_RX_NEW}, {"RX_RESUME", CT_RX_RESUME}, {"RX_TAKEN", CT_RX_TAKEN},
        {"RX_OVER_LIMIT", CT_RX_OVER_LIMIT}};
    size_t k;
    if (PyType_Ready(&RxDecodeType) < 0)
        return -1;
    Py_INCREF(&RxDecodeType);
    if (PyModule_AddObject(m, "RxDecode", (PyObject *)&RxDecodeType) < 0) {
        Py_DECREF(&RxDecodeType);
        return -1;
    }
    if (ct_py_add_type(m, &RxRouteType, "RxRoute") < 0)
        return -1;
    for (k = 0; k < sizeof ints / sizeof ints[0]; ++k)
        if (PyModule_AddIntConstant(m, ints[k].name, ints[k].value) < 0)
            return -1;
    return 0;
}
