/*
 * CPython glue of the fusion filter's update and replay kernels (src/fusion.c, ct_fusion.h):
 * FusionMeas (a measurement model's evaluate bound to the shadow state, the snapshot and the
 * update's y), FusState (InsState.correct and copy_from bound to one state's buffers) and
 * Replay (FusionFilter.step's replay bound to the shadow, the IMU ring and the shadow history).
 * The arrays are bound once through the buffer protocol; the per-call methods use METH_FASTCALL
 * and create no Python object (they return None or a small int).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_fusion.h"

int ct_register_fusion(PyObject *m);

#define FU_MAXBUF 20

/* a C-contiguous buffer of at least n items of 8 bytes, float64 ('d') or int64 ('q', 'l') */
static int fu_get(PyObject *obj, Py_ssize_t n, int writable, int int64, Py_buffer *view, const char *what)
{
    return ct_py_buffer(obj, n, 8, int64 ? "ql" : "d", writable, view, what);
}

/* n doubles of a small argument (a float64 array of any strides and at most 2 dimensions, read in
 * place; else a sequence of numbers or of sequences of numbers, an integer array too) into out[n],
 * row-major */
static int fu_small(PyObject *obj, Py_ssize_t n, double *out, const char *what)
{
    Py_buffer v;
    Py_ssize_t i, j, k = 0;
    if (PyObject_CheckBuffer(obj)) {
        const char *f;
        if (PyObject_GetBuffer(obj, &v, PyBUF_RECORDS_RO) < 0)
            return -1;
        f = v.format;
        if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<'))
            f++;
        if (f == NULL || f[0] != 'd' || f[1] != '\0' || v.itemsize != 8 || v.ndim > 2 || v.len != n * 8) {
            /* another item type or shape: read it as numbers below (slow, not the firmware's path) */
            PyBuffer_Release(&v);
            goto numbers;
        }
        if (v.ndim == 0) {
            memcpy(out, v.buf, 8);
        } else if (v.ndim == 1) {
            for (i = 0; i < n; ++i)
                memcpy(&out[i], (const char *)v.buf + i * v.strides[0], 8);
        } else {
            for (i = 0; i < v.shape[0]; ++i)
                for (j = 0; j < v.shape[1]; ++j)
                    memcpy(&out[k++], (const char *)v.buf + i * v.strides[0] + j * v.strides[1], 8);
        }
        PyBuffer_Release(&v);
        return 0;
    }
numbers:
    {
        PyObject *seq = PySequence_Fast(obj, what);
        Py_ssize_t len;
        if (seq == NULL)
            return -1;
        len = PySequence_Fast_GET_SIZE(seq);
        for (i = 0; i < len; ++i) {
            PyObject *it = PySequence_Fast_GET_ITEM(seq, i);
            if (!PySequence_Check(it)) {             /* a number (a numpy scalar too) */
                if (k >= n)
                    break;
                out[k++] = PyFloat_AsDouble(it);
            } else {
                PyObject *row = PySequence_Fast(it, what);
                if (row == NULL) {
                    Py_DECREF(seq);
                    return -1;
                }
                for (j = 0; j < PySequence_Fast_GET_SIZE(row) && k < n; ++j)
                    out[k++] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(row, j));
                Py_DECREF(row);
            }
            if (PyErr_Occurred()) {
                Py_DECREF(seq);
                return -1;
            }
        }
        Py_DECREF(seq);
        if (k != n) {
            PyErr_Format(PyExc_TypeError, "%s: needs %zd numbers", what, n);
            return -1;
        }
        return 0;
    }
}

/* bind nb buffers (o[i], len[i] items, writable wr[i], int64 i64[i]) into views / ptr */
static int fu_bind(int nb, PyObject **o, const Py_ssize_t *len, const int *wr, const int *i64, const char **names,
                   Py_buffer *views, void **ptr)
{
    int i;
    for (i = 0; i < nb; ++i) {
        if (fu_get(o[i], len[i], wr[i], i64 ? i64[i] : 0, &views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&views[i]);
            return -1;
        }
        ptr[i] = views[i].buf;
    }
    return 0;
}

typedef struct {
    PyObject_HEAD
    Py_buffer views[FU_MAXBUF];
    int nviews;
} FuBase;

static void Fu_dealloc(PyObject *o)
{
    FuBase *self = (FuBase *)o;
    int i;
    for (i = 0; i < self->nviews; ++i)
        PyBuffer_Release(&self->views[i]);
    Py_TYPE(o)->tp_free(o);
}

static int fu_check_unbound(FuBase *self, const char *what)
{
    if (self->nviews) {
        PyErr_Format(PyExc_RuntimeError, "%s: already bound", what);
        return -1;
    }
    return 0;
}

static int fu_check_bound(FuBase *self, const char *what)
{
    if (!self->nviews) {
        PyErr_Format(PyExc_RuntimeError, "%s: not bound", what);
        return -1;
    }
    return 0;
}

/* ---------------------------------------------------------------- FusionMeas */
typedef struct {
    FuBase b;
    struct ct_fusmeas m;
    int xi_model;
    const double *Phi, *Xi, *XiP, *p, *Th;
    double *P, *y, *Psi;
} FusionMeasObject;

static int FusionMeas_init(FusionMeasObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "zp", "zpsi", "zxi", "q0", "s0", "x0", "cp", "co", "xi_model", "mag_var_scale",
                             "xi_var_scale", "xi_floor2", "xi_heading_floor2", "psi_var", "Phi", "Xi", "XiP", "p",
                             "Th", "P", "y", "Psi", NULL};
    static const char *names[8] = {"Phi", "Xi", "XiP", "p", "Th", "P", "y", "Psi"};
    static const int wr[8] = {0, 0, 0, 0, 0, 1, 1, 1};
    struct ct_fusmeas *m = &self->m;
    PyObject *o[8];
    Py_ssize_t len[8];
    void *ptr[8];
    int rows;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiiiiiiiiidddddOOOOOOOO", kwlist, &m->n, &m->zp, &m->zpsi, &m->zxi,
                                     &m->q0, &m->s0, &m->x0, &m->cp, &m->co, &self->xi_model, &m->mag_var_scale,
                                     &m->xi_var_scale, &m->xi_floor2, &m->xi_heading_floor2, &m->psi_var, &o[0],
                                     &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7]))
        return -1;
    if (fu_check_unbound(&self->b, "FusionMeas") < 0)
        return -1;
    rows = 3 + (m->zpsi >= 0 ? 3 : 0) + (m->zxi >= 0 ? 3 : 0);
    if (m->n < 1 || m->n > 256 || m->zp < 0 || m->zp + 3 > rows || m->zpsi + 3 > rows || m->zxi + 3 > rows ||
        (m->zpsi < 0 && m->zxi < 0) || (self->xi_model && (m->zxi < 0 || m->x0 < 0)) ||
        (!self->xi_model && m->zpsi < 0) || m->q0 < 0 || m->q0 + 3 > m->n || m->s0 < 0 || m->s0 + 3 > m->n ||
        m->x0 + 3 > m->n || m->cp < 0 || m->cp + 3 > 6 || m->co < 0 || m->co + 3 > 6) {
        PyErr_SetString(PyExc_ValueError, "FusionMeas: bad state size or row indices");
        return -1;
    }
    len[0] = len[1] = len[2] = len[4] = len[7] = 9;
    len[3] = 3;
    len[5] = (Py_ssize_t)m->n * m->n;
    len[6] = rows;
    if (fu_bind(8, o, len, wr, NULL, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 8;
    self->Phi = ptr[0];
    self->Xi = ptr[1];
    self->XiP = ptr[2];
    self->p = ptr[3];
    self->Th = ptr[4];
    self->P = ptr[5];
    self->y = ptr[6];
    self->Psi = ptr[7];
    return 0;
}

/* evaluate(q, R_ms, C) */
static PyObject *FusionMeas_evaluate(FusionMeasObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double q[3], R[9], C[36];
    if (fu_check_bound(&self->b, "FusionMeas") < 0)
        return NULL;
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "evaluate() takes 3 arguments (%zd given)", nargs);
        return NULL;
    }
    if (fu_small(args[0], 3, q, "q") < 0 || fu_small(args[1], 9, R, "R_ms") < 0 || fu_small(args[2], 36, C, "C") < 0)
        return NULL;
    ct_fusion_evaluate(&self->m, self->xi_model, self->Phi, self->Xi, self->XiP, q, R, C, self->p, self->Th,
                       self->P, self->y, self->Psi);
    Py_RETURN_NONE;
}

static PyMethodDef FusionMeas_methods[] = {
    {"evaluate", (PyCFunction)(void (*)(void))FusionMeas_evaluate, METH_FASTCALL,
     "evaluate(q, R_ms, C): the measurement model's innovation into y and the white blocks of P"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FusionMeasType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FusionMeas",
    .tp_basicsize = sizeof(FusionMeasObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FusionMeas(n, zp, zpsi, zxi, q0, s0, x0, cp, co, xi_model, mag_var_scale, xi_var_scale, xi_floor2, "
              "xi_heading_floor2, psi_var, Phi, Xi, XiP, p, Th, P, y, Psi): fusion_measurement's evaluate bound "
              "to the shadow state, the snapshot and the update's y",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FusionMeas_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = FusionMeas_methods,
};

/* ---------------------------------------------------------------- FusState */
typedef struct {
    FuBase b;
    struct ct_fusstate s;
} FusStateObject;

static PyTypeObject FusStateType;

static int FusState_init(FusStateObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "p", "v", "Th", "ba", "bg", "P", NULL};
    static const char *names[6] = {"p", "v", "Th", "ba", "bg", "P"};
    static const int wr[6] = {1, 1, 1, 1, 1, 1};
    PyObject *o[6];
    Py_ssize_t len[6];
    void *ptr[6];
    int n;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOO", kwlist, &n, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return -1;
    if (fu_check_unbound(&self->b, "FusState") < 0)
        return -1;
    if (n < CT_GYR + 3 || n > 256) {
        PyErr_Format(PyExc_ValueError, "FusState: n must be in %d..256, got %d", CT_GYR + 3, n);
        return -1;
    }
    len[0] = len[1] = len[3] = len[4] = 3;
    len[2] = 9;
    len[5] = (Py_ssize_t)n * n;
    if (fu_bind(6, o, len, wr, NULL, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 6;
    self->s.n = n;
    self->s.p = ptr[0];
    self->s.v = ptr[1];
    self->s.Th = ptr[2];
    self->s.ba = ptr[3];
    self->s.bg = ptr[4];
    self->s.P = ptr[5];
    return 0;
}

/* correct(dx): dx a float64 array of n items (read in place) */
static PyObject *FusState_correct(FusStateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer v;
    if (fu_check_bound(&self->b, "FusState") < 0)
        return NULL;
    if (nargs != 1) {
        PyErr_Format(PyExc_TypeError, "correct() takes 1 argument (%zd given)", nargs);
        return NULL;
    }
    if (fu_get(args[0], self->s.n, 0, 0, &v, "dx") < 0)
        return NULL;
    ct_fusion_correct(&self->s, (const double *)v.buf);
    PyBuffer_Release(&v);
    Py_RETURN_NONE;
}

/* copy_from(other): the other state's nominal state and covariance */
static PyObject *FusState_copy_from(FusStateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    FusStateObject *other;
    if (fu_check_bound(&self->b, "FusState") < 0)
        return NULL;
    if (nargs != 1 || !PyObject_TypeCheck(args[0], &FusStateType)) {
        PyErr_SetString(PyExc_TypeError, "copy_from() takes one FusState");
        return NULL;
    }
    other = (FusStateObject *)args[0];
    if (fu_check_bound(&other->b, "FusState") < 0)
        return NULL;
    if (other->s.n != self->s.n) {
        PyErr_SetString(PyExc_ValueError, "copy_from: states of different sizes");
        return NULL;
    }
    ct_fusion_copy(&self->s, &other->s);
    Py_RETURN_NONE;
}

static PyMethodDef FusState_methods[] = {
    {"correct", (PyCFunction)(void (*)(void))FusState_correct, METH_FASTCALL,
     "correct(dx): InsState.correct (p, v, offsets added; Theta <- exp([dx_ori]x) Theta)"},
    {"copy_from", (PyCFunction)(void (*)(void))FusState_copy_from, METH_FASTCALL,
     "copy_from(other): InsState.copy_from's arrays (the time is the caller's)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FusStateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FusState",
    .tp_basicsize = sizeof(FusStateObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FusState(n, p, v, Th, ba, bg, P): InsState.correct and copy_from bound to one state's buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FusState_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = FusState_methods,
};

/* ---------------------------------------------------------------- Replay */
#define RP_NBUF 15
typedef struct {
    FuBase b;
    struct ct_replay r;
    double E[9];
    int64_t *io;
    double *fo;
    const int64_t *imu_hc;          /* the IMU ring's (head, count), or NULL: io carries them */
    int64_t *hist_hc;               /* the history's (head, count), advanced here, or NULL */
    PyObject *snap_state, *snap_aux;    /* bind_snapshot's FusState and SnapAux (references held), or NULL */
} ReplayObject;

static int Replay_init(ReplayObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "p", "v", "Th", "ba", "bg", "A", "P", "Q", "T", "imu_t", "imu_d", "hist_t",
                             "hist_d", "io", "fo", "fixed", "dtk", "symmetrize_every", "imu_hc", "hist_hc", NULL};
    static const char *names[RP_NBUF] = {"p", "v", "Th", "ba", "bg", "A", "P", "Q", "T", "imu_t", "imu_d",
                                         "hist_t", "hist_d", "io", "fo"};
    static const int wr[RP_NBUF] = {1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 1};
    static const int i64[RP_NBUF] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 1, 0, 1, 0};
    struct ct_replay *r = &self->r;
    PyObject *o[RP_NBUF], *dtk, *ohc[2] = {Py_None, Py_None};
    Py_ssize_t len[RP_NBUF];
    void *ptr[RP_NBUF];
    Py_buffer tv;
    int n, fixed, sym, i, icap, hcap;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOOOOOOOOOOOpOi|OO", kwlist, &n, &o[0], &o[1], &o[2], &o[3],
                                     &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12], &o[13], &o[14],
                                     &fixed, &dtk, &sym, &ohc[0], &ohc[1]))
        return -1;
    if ((ohc[0] == Py_None) != (ohc[1] == Py_None)) {
        PyErr_SetString(PyExc_TypeError, "Replay: imu_hc and hist_hc go together");
        return -1;
    }
    if (fu_check_unbound(&self->b, "Replay") < 0)
        return -1;
    if (n < CT_GYR + 3 || n > 256 || sym < 1) {
        PyErr_Format(PyExc_ValueError, "Replay: n must be in %d..256 and symmetrize_every >= 1", CT_GYR + 3);
        return -1;
    }
    if (fu_small(dtk, 6, r->dtk, "dtk") < 0)
        return -1;
    /* the rings' capacities from their time arrays */
    if (fu_get(o[9], 2, 0, 1, &tv, "imu_t") < 0)
        return -1;
    icap = (int)(tv.len / 8);
    PyBuffer_Release(&tv);
    if (fu_get(o[11], 2, 1, 1, &tv, "hist_t") < 0)
        return -1;
    hcap = (int)(tv.len / 8);
    PyBuffer_Release(&tv);
    for (i = 0; i < 5; ++i)
        len[i] = i == 2 ? 9 : 3;
    for (i = 5; i < 9; ++i)
        len[i] = (Py_ssize_t)n * n;
    len[9] = icap;
    len[10] = (Py_ssize_t)icap * CT_IMU_WIDTH;
    len[11] = hcap;
    len[12] = (Py_ssize_t)hcap * CT_HIST_WIDTH;
    len[13] = CT_RIO_N;
    len[14] = CT_RFO_N;
    if (fu_bind(RP_NBUF, o, len, wr, i64, names, self->b.views, ptr) < 0)
        return -1;
    if (self->b.views[10].len != len[10] * 8 || self->b.views[12].len != len[12] * 8) {
        for (i = 0; i < RP_NBUF; ++i)
            PyBuffer_Release(&self->b.views[i]);
        PyErr_SetString(PyExc_ValueError, "Replay: the IMU ring needs 18 columns, the pose history 12");
        return -1;
    }
    self->b.nviews = RP_NBUF;
    self->imu_hc = NULL;
    self->hist_hc = NULL;
    if (ohc[0] != Py_None) {
        /* the rings' head and count (fusion_rings.KernelRing.hc), read and advanced by replay() */
        if (fu_get(ohc[0], 2, 0, 1, &self->b.views[RP_NBUF], "imu_hc") < 0)
            return -1;                  /* (the bound views are released by the deallocation) */
        self->b.nviews = RP_NBUF + 1;
        if (fu_get(ohc[1], 2, 1, 1, &self->b.views[RP_NBUF + 1], "hist_hc") < 0)
            return -1;
        self->b.nviews = RP_NBUF + 2;
        self->imu_hc = self->b.views[RP_NBUF].buf;
        self->hist_hc = self->b.views[RP_NBUF + 1].buf;
    }
    r->ins.n = n;
    r->ins.p = ptr[0];
    r->ins.v = ptr[1];
    r->ins.Th = ptr[2];
    r->ins.ba = ptr[3];
    r->ins.bg = ptr[4];
    r->ins.A = ptr[5];
    r->ins.P = ptr[6];
    r->ins.Q = ptr[7];
    r->Qd = ptr[7];
    r->ins.T = ptr[8];
    r->ins.E = self->E;
    r->imu_t = ptr[9];
    r->imu_d = ptr[10];
    r->hist_t = ptr[11];
    r->hist_d = ptr[12];
    r->imu_cap = icap;
    r->hist_cap = hcap;
    r->fixed = fixed;
    r->symmetrize_every = sym;
    self->io = ptr[13];
    self->fo = ptr[14];
    return 0;
}

/* one ct_fusion_replay call with the rings' positions taken from and given back to their (head, count) */
static int replay_once(ReplayObject *self, int budget)
{
    int64_t *io = self->io;
    int rc;
    if (self->imu_hc != NULL) {
        /* Ring.slot(0) and len of the IMU ring and of the history, from their (head, count) */
        int64_t f = self->imu_hc[0] - self->imu_hc[1];
        io[CT_RIO_IMU_FIRST] = f < 0 ? f + self->r.imu_cap : f;
        io[CT_RIO_IMU_COUNT] = self->imu_hc[1];
        f = self->hist_hc[0] - self->hist_hc[1];
        io[CT_RIO_HIST_FIRST] = f < 0 ? f + self->r.hist_cap : f;
        io[CT_RIO_HIST_COUNT] = self->hist_hc[1];
    }
    if (io[CT_RIO_IMU_COUNT] < 0 || io[CT_RIO_IMU_COUNT] > self->r.imu_cap || io[CT_RIO_IMU_FIRST] < 0 ||
        io[CT_RIO_IMU_FIRST] >= self->r.imu_cap || io[CT_RIO_HIST_COUNT] < 0 ||
        io[CT_RIO_HIST_COUNT] > self->r.hist_cap || io[CT_RIO_HIST_FIRST] < 0 ||
        io[CT_RIO_HIST_FIRST] >= self->r.hist_cap || io[CT_RIO_SPLIT] >= self->r.imu_cap) {
        PyErr_SetString(PyExc_ValueError, "replay: ring slots or counts out of range");
        return -1;
    }
    rc = ct_fusion_replay(&self->r, io, self->fo, budget);
    if (self->hist_hc != NULL) {
        /* ring.Ring.advance(io[CT_RIO_HIST_PUSHED]) */
        const int64_t cap = self->r.hist_cap, c = self->hist_hc[1] + io[CT_RIO_HIST_PUSHED];
        self->hist_hc[0] = (self->hist_hc[0] + io[CT_RIO_HIST_PUSHED]) % cap;
        self->hist_hc[1] = c < cap ? c : cap;
    }
    return rc;
}

static long replay_budget(PyObject *o)
{
    long budget = PyLong_AsLong(o);
    if (budget > 1L << 30)
        budget = 1L << 30;
    return budget;
}

/* replay(budget) -> CT_REPLAY_* (the bound io and fo carry the rest) */
static PyObject *Replay_replay(ReplayObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long budget;
    int rc;
    if (fu_check_bound(&self->b, "Replay") < 0)
        return NULL;
    if (nargs != 1) {
        PyErr_Format(PyExc_TypeError, "replay() takes 1 argument (%zd given)", nargs);
        return NULL;
    }
    budget = replay_budget(args[0]);
    if (budget == -1 && PyErr_Occurred())
        return NULL;
    rc = replay_once(self, (int)budget);
    if (rc < 0)
        return NULL;
    return PyLong_FromLong(rc);
}

static PyObject *Replay_bind_snapshot(ReplayObject *self, PyObject *const *args, Py_ssize_t nargs);
static PyObject *Replay_replay_take(ReplayObject *self, PyObject *const *args, Py_ssize_t nargs);

static void Replay_dealloc(PyObject *o)
{
    ReplayObject *self = (ReplayObject *)o;
    Py_CLEAR(self->snap_state);
    Py_CLEAR(self->snap_aux);
    Fu_dealloc(o);
}

static PyMethodDef Replay_methods[] = {
    {"replay", (PyCFunction)(void (*)(void))Replay_replay, METH_FASTCALL,
     "replay(budget) -> REPLAY_*: FusionFilter.step's replay on the shadow state (io, fo: its attributes)"},
    {"bind_snapshot", (PyCFunction)(void (*)(void))Replay_bind_snapshot, METH_FASTCALL,
     "bind_snapshot(state, aux): the snapshot's FusState and SnapAux, for replay_take"},
    {"replay_take", (PyCFunction)(void (*)(void))Replay_replay_take, METH_FASTCALL,
     "replay_take(budget, xi) -> REPLAY_*: replay, a snapshot falling inside it taken here (the state copied into "
     "the bound snapshot state, SnapAux.take with xi) and the replay resumed"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ReplayType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Replay",
    .tp_basicsize = sizeof(ReplayObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Replay(n, p, v, Th, ba, bg, A, P, Q, T, imu_t, imu_d, hist_t, hist_d, io, fo, fixed, dtk, "
              "symmetrize_every, imu_hc=None, hist_hc=None): the fusion filter's replay bound to the shadow state "
              "and its rings (with the rings' head and count arrays, replay() reads them and advances the "
              "history's itself)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Replay_init,
    .tp_dealloc = Replay_dealloc,
    .tp_methods = Replay_methods,
};

/* ---------------------------------------------------------------- SnapAux */
typedef struct {
    FuBase b;
    int fixed, np, t0, imu_cap;
    const double *imu_d, *R, *P, *bias;
    double *Phi, *Xi, *XiP, *XiB;
} SnapAuxObject;

static int SnapAux_init(SnapAuxObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"fixed", "np", "t0", "imu_d", "Phi", "Xi", "XiP", "XiB", "R", "P", "bias", NULL};
    static const char *names[8] = {"imu_d", "Phi", "Xi", "XiP", "XiB", "R", "P", "bias"};
    static const int wr[8] = {0, 1, 1, 1, 1, 0, 0, 0};
    PyObject *o[8];
    Py_ssize_t len[8];
    void *ptr[8];
    Py_buffer v;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "piiOOOOOOOO", kwlist, &self->fixed, &self->np, &self->t0, &o[0], &o[1],
                                     &o[2], &o[3], &o[4], &o[5], &o[6], &o[7]))
        return -1;
    if (fu_check_unbound(&self->b, "SnapAux") < 0)
        return -1;
    if (self->np < 3 || self->np > 256 || self->t0 < 0 || self->t0 + 3 > self->np) {
        PyErr_SetString(PyExc_ValueError, "SnapAux: bad orientation state size or theta rows");
        return -1;
    }
    if (fu_get(o[0], CT_IMU_WIDTH, 0, 0, &v, "imu_d") < 0)
        return -1;
    self->imu_cap = (int)(v.len / (8 * CT_IMU_WIDTH));
    PyBuffer_Release(&v);
    len[0] = (Py_ssize_t)self->imu_cap * CT_IMU_WIDTH;
    len[1] = len[2] = len[3] = len[5] = 9;
    len[4] = len[7] = 3;
    len[6] = (Py_ssize_t)self->np * self->np;
    if (fu_bind(8, o, len, wr, NULL, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 8;
    self->imu_d = ptr[0];
    self->Phi = ptr[1];
    self->Xi = ptr[2];
    self->XiP = ptr[3];
    self->XiB = ptr[4];
    self->R = ptr[5];
    self->P = ptr[6];
    self->bias = ptr[7];
    return 0;
}

/* take(k, xi): Snapshot.take_aux's arrays from IMU row k (and the ch. 2 filter when xi) */
static PyObject *SnapAux_take(SnapAuxObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long k;
    int xi;
    if (fu_check_bound(&self->b, "SnapAux") < 0 || ct_py_nargs("take", nargs, 2) < 0)
        return NULL;
    k = PyLong_AsLong(args[0]);
    if (k == -1 && PyErr_Occurred())
        return NULL;
    xi = PyObject_IsTrue(args[1]);
    if (xi < 0)
        return NULL;
    if (k < 0 || k >= self->imu_cap) {
        PyErr_SetString(PyExc_ValueError, "take: IMU slot out of range");
        return NULL;
    }
    ct_fusion_snap_aux(self->fixed, self->imu_d + (Py_ssize_t)k * CT_IMU_WIDTH, xi, self->R, self->P, self->np,
                       self->t0, self->bias, self->Phi, self->Xi, self->XiP, self->XiB);
    Py_RETURN_NONE;
}

static PyMethodDef SnapAux_methods[] = {
    {"take", (PyCFunction)(void (*)(void))SnapAux_take, METH_FASTCALL,
     "take(k, xi): Snapshot.take_aux's Phi (IMU row k) and, when xi, Xi, its covariance and offset"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SnapAuxType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SnapAux",
    .tp_basicsize = sizeof(SnapAuxObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SnapAux(fixed, np, t0, imu_d, Phi, Xi, XiP, XiB, R, P, bias): the snapshot's source orientation "
              "and ch. 2 filter, bound to the IMU ring, the snapshot and the filter",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SnapAux_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = SnapAux_methods,
};

/* ---------------------------------------------------------------- Replay's snapshot */
/* bind_snapshot(state, aux): a FusState (the snapshot's state) and a SnapAux */
static PyObject *Replay_bind_snapshot(ReplayObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (fu_check_bound(&self->b, "Replay") < 0 || ct_py_nargs("bind_snapshot", nargs, 2) < 0)
        return NULL;
    if (!PyObject_TypeCheck(args[0], &FusStateType) || !PyObject_TypeCheck(args[1], &SnapAuxType) ||
        fu_check_bound(&((FusStateObject *)args[0])->b, "FusState") < 0 ||
        fu_check_bound(&((SnapAuxObject *)args[1])->b, "SnapAux") < 0) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "bind_snapshot() takes a FusState and a SnapAux");
        return NULL;
    }
    if (((FusStateObject *)args[0])->s.n != self->r.ins.n || ((SnapAuxObject *)args[1])->imu_cap != self->r.imu_cap) {
        PyErr_SetString(PyExc_ValueError, "bind_snapshot: another state size or IMU ring");
        return NULL;
    }
    Py_INCREF(args[0]);
    Py_INCREF(args[1]);
    Py_XSETREF(self->snap_state, args[0]);
    Py_XSETREF(self->snap_aux, args[1]);
    Py_RETURN_NONE;
}

/* replay_take's work once its arguments are read: the kernel's stop, or -1 with an exception set */
static int replay_take_once(ReplayObject *self, int budget, int xi)
{
    int rc;
    int64_t steps;
    rc = replay_once(self, budget);
    if (rc == CT_REPLAY_SNAPSHOT) {
        const struct ct_ins *s = &self->r.ins;
        const struct ct_fusstate src = {s->n, s->p, s->v, s->Th, s->ba, s->bg, s->P};
        const SnapAuxObject *a = (const SnapAuxObject *)self->snap_aux;
        const int64_t k = self->io[CT_RIO_SPLIT];
        ct_fusion_copy(&((FusStateObject *)self->snap_state)->s, &src);
        ct_fusion_snap_aux(a->fixed, a->imu_d + (Py_ssize_t)k * CT_IMU_WIDTH, xi, a->R, a->P, a->np, a->t0, a->bias,
                           a->Phi, a->Xi, a->XiP, a->XiB);
        self->io[CT_RIO_SNAP_PENDING] = 0;          /* taken: Snapshot.pending */
        steps = self->io[CT_RIO_STEPS];
        rc = replay_once(self, budget);
        self->io[CT_RIO_STEPS] += steps;
    }
    return rc;
}

/* replay_take(budget, xi): FusionFilter._advance's snapshot in the replay (Snapshot.take: InsState.copy_from,
 * take_aux) between the two calls CompiledReplay.run makes around it; io's steps are the sum of both */
static PyObject *Replay_replay_take(ReplayObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long budget;
    int xi, rc;
    if (fu_check_bound(&self->b, "Replay") < 0 || ct_py_nargs("replay_take", nargs, 2) < 0)
        return NULL;
    if (self->snap_state == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "replay_take: no snapshot bound");
        return NULL;
    }
    budget = replay_budget(args[0]);
    if (budget == -1 && PyErr_Occurred())
        return NULL;
    xi = PyObject_IsTrue(args[1]);
    if (xi < 0)
        return NULL;
    rc = replay_take_once(self, (int)budget, xi);
    if (rc < 0)
        return NULL;
    return PyLong_FromLong(rc);
}

int ct_py_replay_takes(PyObject *o)
{
    ReplayObject *self = (ReplayObject *)o;
    return PyObject_TypeCheck(o, &ReplayType) && self->b.nviews > 0 && self->snap_state != NULL &&
           self->imu_hc != NULL;
}

int ct_py_replay_split_take(PyObject *o, int64_t t0, int64_t pending, int64_t snap_t, int64_t pcount, int xi,
                            int64_t *io_out)
{
    ReplayObject *self = (ReplayObject *)o;
    int64_t *io = self->io;
    int rc;
    io[CT_RIO_UNITS] = 0;                       /* CompiledReplay.split_take's io */
    io[CT_RIO_SPLIT] = -1;
    io[CT_RIO_T] = t0;
    io[CT_RIO_SNAP_PENDING] = pending;
    io[CT_RIO_SNAP_T] = snap_t;
    io[CT_RIO_PRED_COUNT] = pcount;
    rc = replay_take_once(self, 1, xi);
    io_out[0] = io[CT_RIO_T];
    io_out[1] = io[CT_RIO_PRED_COUNT];
    io_out[2] = io[CT_RIO_STEPS];
    io_out[3] = io[CT_RIO_SNAP_PENDING];
    return rc;
}

/* ---------------------------------------------------------------- PoseAt */
typedef struct {
    FuBase b;
    int64_t cap;
    const int64_t *ht, *hc;
    const double *hd;
} PoseAtObject;

static int PoseAt_init(PoseAtObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"hist_t", "hist_d", "hc", NULL};
    static const char *names[3] = {"hist_t", "hist_d", "hc"};
    static const int wr[3] = {0, 0, 0};
    static const int i64[3] = {1, 0, 1};
    PyObject *o[3];
    Py_ssize_t len[3];
    void *ptr[3];
    Py_buffer v;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOO", kwlist, &o[0], &o[1], &o[2]))
        return -1;
    if (fu_check_unbound(&self->b, "PoseAt") < 0)
        return -1;
    if (fu_get(o[0], 2, 0, 1, &v, "hist_t") < 0)
        return -1;
    self->cap = (int64_t)(v.len / 8);
    PyBuffer_Release(&v);
    len[0] = (Py_ssize_t)self->cap;
    len[1] = (Py_ssize_t)self->cap * CT_HIST_WIDTH;
    len[2] = 2;
    if (fu_bind(3, o, len, wr, i64, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 3;
    self->ht = ptr[0];
    self->hd = ptr[1];
    self->hc = ptr[2];
    return 0;
}

/* at(t_us, out_p, out_R) -> bool */
static PyObject *PoseAt_at(PoseAtObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t;
    Py_buffer vp, vr;
    int ok;
    if (fu_check_bound(&self->b, "PoseAt") < 0 || ct_py_nargs("at", nargs, 3) < 0 || ct_py_int64(args[0], &t) < 0)
        return NULL;
    if (self->hc[0] < 0 || self->hc[0] >= self->cap || self->hc[1] < 0 || self->hc[1] > self->cap) {
        PyErr_SetString(PyExc_ValueError, "at: the history's head or count out of range");
        return NULL;
    }
    if (fu_get(args[1], 3, 1, 0, &vp, "out_p") < 0)
        return NULL;
    if (fu_get(args[2], 9, 1, 0, &vr, "out_R") < 0) {
        PyBuffer_Release(&vp);
        return NULL;
    }
    ok = ct_fusion_pose_at(self->ht, self->hd, self->cap, self->hc[0], self->hc[1], t, (double *)vp.buf,
                           (double *)vr.buf);
    PyBuffer_Release(&vp);
    PyBuffer_Release(&vr);
    if (ok)
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef PoseAt_methods[] = {
    {"at", (PyCFunction)(void (*)(void))PoseAt_at, METH_FASTCALL,
     "at(t_us, out_p, out_R) -> bool: PoseHistory.pose_at over the bound history"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject PoseAtType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.PoseAt",
    .tp_basicsize = sizeof(PoseAtObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "PoseAt(hist_t, hist_d, hc): the pose history's interpolation bound to a KernelRing",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)PoseAt_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = PoseAt_methods,
};

/* ---------------------------------------------------------------- MotionCov */
typedef struct {
    FuBase b;
    int n;
    double tr2;
    const double *P, *v, *w;
} MotionCovObject;

static int MotionCov_init(MotionCovObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "tr2", "P", "v", "w", NULL};
    static const char *names[3] = {"P", "v", "w"};
    static const int wr[3] = {0, 0, 0};
    PyObject *o[3];
    Py_ssize_t len[3];
    void *ptr[3];
    if (!PyArg_ParseTupleAndKeywords(args, kw, "idOOO", kwlist, &self->n, &self->tr2, &o[0], &o[1], &o[2]))
        return -1;
    if (fu_check_unbound(&self->b, "MotionCov") < 0)
        return -1;
    if (self->n < CT_GYR + 3 || self->n > 256) {
        PyErr_Format(PyExc_ValueError, "MotionCov: n must be in %d..256", CT_GYR + 3);
        return -1;
    }
    len[0] = (Py_ssize_t)self->n * self->n;
    len[1] = len[2] = 3;
    if (fu_bind(3, o, len, wr, NULL, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 3;
    self->P = ptr[0];
    self->v = ptr[1];
    self->w = ptr[2];
    return 0;
}

/* into(C, compensated, out, p, initialized) */
static PyObject *MotionCov_into(MotionCovObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vc, vo, vp;
    int comp, init;
    if (fu_check_bound(&self->b, "MotionCov") < 0 || ct_py_nargs("into", nargs, 5) < 0)
        return NULL;
    comp = PyObject_IsTrue(args[1]);
    init = PyObject_IsTrue(args[4]);
    if (comp < 0 || init < 0)
        return NULL;
    if (fu_get(args[0], 36, 0, 0, &vc, "C") < 0)
        return NULL;
    if (fu_get(args[2], 36, 1, 0, &vo, "out") < 0) {
        PyBuffer_Release(&vc);
        return NULL;
    }
    if (fu_get(args[3], 3, 0, 0, &vp, "p") < 0) {
        PyBuffer_Release(&vc);
        PyBuffer_Release(&vo);
        return NULL;
    }
    ct_fusion_motion_cov((const double *)vc.buf, (double *)vo.buf, (const double *)vp.buf, comp, init, self->tr2,
                         self->P, self->n, self->v, self->w);
    PyBuffer_Release(&vc);
    PyBuffer_Release(&vo);
    PyBuffer_Release(&vp);
    Py_RETURN_NONE;
}

static PyMethodDef MotionCov_methods[] = {
    {"into", (PyCFunction)(void (*)(void))MotionCov_into, METH_FASTCALL,
     "into(C, compensated, out, p, initialized): SensorInertial.motion_cov with the bound live state"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject MotionCovType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.MotionCov",
    .tp_basicsize = sizeof(MotionCovObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "MotionCov(n, tr2, P, v, w): a burst's motion covariance bound to the live state and the rate",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)MotionCov_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = MotionCov_methods,
};

/* ---------------------------------------------------------------- Compensate */
typedef struct {
    FuBase b;
    int n, n_st;
    int64_t cap;
    double max_sigma;
    double *S_comp, *p_ref, *R_ref, *p_j, *R_j;
    const double *h_ref, *h_j, *P, *hd;
    const int64_t *ht, *hc;
} CompensateObject;

static int Compensate_init(CompensateObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "n_st", "max_sigma", "S_comp", "h_ref", "h_j", "p_ref", "R_ref", "p_j", "R_j", "P",
                             "hist_t", "hist_d", "hc", NULL};
    static const char *names[11] = {"S_comp", "h_ref", "h_j", "p_ref", "R_ref", "p_j", "R_j", "P", "hist_t",
                                    "hist_d", "hc"};
    static const int wr[11] = {1, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0};
    static const int i64[11] = {0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 1};
    PyObject *o[11];
    Py_ssize_t len[11];
    void *ptr[11];
    Py_buffer v;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iidOOOOOOOOOOO", kwlist, &self->n, &self->n_st, &self->max_sigma,
                                     &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10]))
        return -1;
    if (fu_check_unbound(&self->b, "Compensate") < 0)
        return -1;
    if (self->n < 1 || self->n > 64 || self->n_st < CT_GYR + 3 || self->n_st > 256) {
        PyErr_SetString(PyExc_ValueError, "Compensate: bad pulse count or state size");
        return -1;
    }
    if (fu_get(o[8], 2, 0, 1, &v, "hist_t") < 0)
        return -1;
    self->cap = (int64_t)(v.len / 8);
    PyBuffer_Release(&v);
    len[0] = len[1] = len[2] = 3 * (Py_ssize_t)self->n;
    len[3] = len[5] = 3;
    len[4] = len[6] = 9;
    len[7] = (Py_ssize_t)self->n_st * self->n_st;
    len[8] = (Py_ssize_t)self->cap;
    len[9] = (Py_ssize_t)self->cap * CT_HIST_WIDTH;
    len[10] = 2;
    if (fu_bind(11, o, len, wr, i64, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = 11;
    self->S_comp = ptr[0];
    self->h_ref = ptr[1];
    self->h_j = ptr[2];
    self->p_ref = ptr[3];
    self->R_ref = ptr[4];
    self->p_j = ptr[5];
    self->R_j = ptr[6];
    self->P = ptr[7];
    self->ht = ptr[8];
    self->hd = ptr[9];
    self->hc = ptr[10];
    return 0;
}

static int comp_ring_ok(CompensateObject *self)
{
    if (self->hc[0] < 0 || self->hc[0] >= self->cap || self->hc[1] < 0 || self->hc[1] > self->cap) {
        PyErr_SetString(PyExc_ValueError, "Compensate: the history's head or count out of range");
        return 0;
    }
    return 1;
}

/* begin(S, initialized, t_ref) -> bool */
static PyObject *Compensate_begin(CompensateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vs;
    int init, ok;
    int64_t t;
    if (fu_check_bound(&self->b, "Compensate") < 0 || ct_py_nargs("begin", nargs, 3) < 0 || !comp_ring_ok(self))
        return NULL;
    init = PyObject_IsTrue(args[1]);
    if (init < 0 || ct_py_int64(args[2], &t) < 0)
        return NULL;
    if (fu_get(args[0], 3 * (Py_ssize_t)self->n, 0, 0, &vs, "S") < 0)
        return NULL;
    ok = ct_fusion_comp_begin((const double *)vs.buf, self->S_comp, self->n, init, self->P, self->n_st,
                              self->max_sigma, self->ht, self->hd, self->cap, self->hc[0], self->hc[1], t,
                              self->p_ref, self->R_ref);
    PyBuffer_Release(&vs);
    if (ok)
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* pulse(t_j) -> bool: the pose at pulse time t_j into p_j, R_j */
static PyObject *Compensate_pulse(CompensateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t;
    if (fu_check_bound(&self->b, "Compensate") < 0 || ct_py_nargs("pulse", nargs, 1) < 0 || !comp_ring_ok(self) ||
        ct_py_int64(args[0], &t) < 0)
        return NULL;
    if (ct_fusion_pose_at(self->ht, self->hd, self->cap, self->hc[0], self->hc[1], t, self->p_j, self->R_j))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* add(j): pulse j's correction */
static PyObject *Compensate_add(CompensateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long j;
    if (fu_check_bound(&self->b, "Compensate") < 0 || ct_py_nargs("add", nargs, 1) < 0)
        return NULL;
    j = PyLong_AsLong(args[0]);
    if (j == -1 && PyErr_Occurred())
        return NULL;
    if (j < 0 || j >= self->n) {
        PyErr_SetString(PyExc_ValueError, "add: pulse index out of range");
        return NULL;
    }
    ct_fusion_comp_add(self->S_comp, self->h_ref, self->h_j, self->n, (int)j);
    Py_RETURN_NONE;
}

static PyMethodDef Compensate_methods[] = {
    {"begin", (PyCFunction)(void (*)(void))Compensate_begin, METH_FASTCALL,
     "begin(S, initialized, t_ref) -> bool: compensate_begin's copy, checks and pose at t_ref"},
    {"pulse", (PyCFunction)(void (*)(void))Compensate_pulse, METH_FASTCALL,
     "pulse(t_j) -> bool: the pose at a pulse's time into p_j, R_j"},
    {"add", (PyCFunction)(void (*)(void))Compensate_add, METH_FASTCALL,
     "add(j): S_comp[:, j] += h_ref[:, j] - h_j[:, j] (in the reference's order)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject CompensateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Compensate",
    .tp_basicsize = sizeof(CompensateObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Compensate(n, n_st, max_sigma, S_comp, h_ref, h_j, p_ref, R_ref, p_j, R_j, P, hist_t, hist_d, hc): "
              "a sensor's motion compensation within a burst bound to its buffers, the live state and history",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Compensate_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = Compensate_methods,
};

/* ---------------------------------------------------------------- HistCopy */
typedef struct {
    FuBase b;
    int64_t cap;
    int64_t *lt, *lhc, *st, *shc;
    double *ld, *sd;
    int64_t *mark;                      /* PoseHistory.mark (ct_hist_sync), or NULL: whole copies */
} HistCopyObject;

static int HistCopy_init(HistCopyObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"live_t", "live_d", "live_hc", "shadow_t", "shadow_d", "shadow_hc", "mark", NULL};
    static const char *names[7] = {"live_t", "live_d", "live_hc", "shadow_t", "shadow_d", "shadow_hc", "mark"};
    static const int wr[7] = {1, 1, 1, 1, 1, 1, 1};
    static const int i64[7] = {1, 0, 1, 1, 0, 1, 1};
    PyObject *o[7] = {NULL, NULL, NULL, NULL, NULL, NULL, NULL};
    Py_ssize_t len[7];
    void *ptr[7];
    Py_buffer v;
    int nb;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOO|O", kwlist, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6]))
        return -1;
    nb = o[6] != NULL && o[6] != Py_None ? 7 : 6;
    if (fu_check_unbound(&self->b, "HistCopy") < 0)
        return -1;
    if (fu_get(o[0], 2, 1, 1, &v, "live_t") < 0)
        return -1;
    self->cap = (int64_t)(v.len / 8);
    PyBuffer_Release(&v);
    len[0] = len[3] = (Py_ssize_t)self->cap;
    len[1] = len[4] = (Py_ssize_t)self->cap * CT_HIST_WIDTH;
    len[2] = len[5] = 2;
    len[6] = CT_HMK_N;
    if (fu_bind(nb, o, len, wr, i64, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = nb;
    if (self->b.views[3].len != self->cap * 8 || self->b.views[1].len != len[1] * 8 ||
        self->b.views[4].len != len[1] * 8) {
        PyErr_SetString(PyExc_ValueError, "HistCopy: two histories of one capacity and 12 columns");
        return -1;                      /* (the bound views are released by the deallocation) */
    }
    self->lt = ptr[0];
    self->ld = ptr[1];
    self->lhc = ptr[2];
    self->st = ptr[3];
    self->sd = ptr[4];
    self->shc = ptr[5];
    self->mark = nb == 7 ? ptr[6] : NULL;
    return 0;
}

static int hist_ok(const int64_t *hc, int64_t cap)
{
    if (hc[0] < 0 || hc[0] >= cap || hc[1] < 0 || hc[1] > cap) {
        PyErr_SetString(PyExc_ValueError, "HistCopy: a history's head or count out of range");
        return 0;
    }
    return 1;
}

static int mark_ok(const int64_t *mark, int64_t cap)
{
    if (mark != NULL && mark[CT_HMK_VALID] && (mark[CT_HMK_LIVE_SLOT] < 0 || mark[CT_HMK_LIVE_SLOT] >= cap ||
                                               mark[CT_HMK_SHADOW_SLOT] < 0 || mark[CT_HMK_SHADOW_SLOT] >= cap)) {
        PyErr_SetString(PyExc_ValueError, "HistCopy: the mark's slots out of range");
        return 0;
    }
    return 1;
}

/* rewind(t_ref): PoseHistory.rewind_shadow */
static PyObject *HistCopy_rewind(HistCopyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t;
    if (fu_check_bound(&self->b, "HistCopy") < 0 || ct_py_nargs("rewind", nargs, 1) < 0 ||
        ct_py_int64(args[0], &t) < 0 || !hist_ok(self->lhc, self->cap) ||
        !hist_ok(self->shc, self->cap) || !mark_ok(self->mark, self->cap))
        return NULL;
    if (self->mark != NULL)
        ct_hist_sync(self->lt, self->ld, self->lhc, self->st, self->sd, self->shc, self->cap, self->mark, 1, t);
    else
        ct_fusion_hist_copy(self->st, self->sd, self->shc, self->lt, self->ld, self->lhc, self->cap, 1, t);
    Py_RETURN_NONE;
}

/* commit(): PoseHistory.commit */
static PyObject *HistCopy_commit(HistCopyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (fu_check_bound(&self->b, "HistCopy") < 0 || ct_py_nargs("commit", nargs, 0) < 0 ||
        !hist_ok(self->shc, self->cap) || !hist_ok(self->lhc, self->cap) || !mark_ok(self->mark, self->cap))
        return NULL;
    if (self->mark != NULL)
        ct_hist_sync(self->lt, self->ld, self->lhc, self->st, self->sd, self->shc, self->cap, self->mark, 0, 0);
    else
        ct_fusion_hist_copy(self->lt, self->ld, self->lhc, self->st, self->sd, self->shc, self->cap, 0, 0);
    Py_RETURN_NONE;
}

static PyMethodDef HistCopy_methods[] = {
    {"rewind", (PyCFunction)(void (*)(void))HistCopy_rewind, METH_FASTCALL,
     "rewind(t_ref): the shadow history = the live one up to t_ref"},
    {"commit", (PyCFunction)(void (*)(void))HistCopy_commit, METH_FASTCALL, "commit(): the live history = the shadow"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject HistCopyType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.HistCopy",
    .tp_basicsize = sizeof(HistCopyObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "HistCopy(live_t, live_d, live_hc, shadow_t, shadow_d, shadow_hc, mark=None): the pose histories' "
              "rewind and commit bound to both rings (with PoseHistory.mark: in part, ct_hist_sync)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)HistCopy_init,
    .tp_dealloc = Fu_dealloc,
    .tp_methods = HistCopy_methods,
};

/* ---------------------------------------------------------------- FusionUpdate */
/* The delayed update's two halves in one call each (FusionFilter._restore and _update_shadow),
 * bound once to the measurement model's FusionMeas, the shadow's and the snapshot's FusState, the
 * pose histories' HistCopy (references kept) and the KalmanUpdate's buffers. */
#define FUP_NBUF 16
typedef struct {
    FuBase b;
    PyObject *refs[4];
    struct ct_fusprep f;
    struct ct_kalman u;
    double *nis;
} FusionUpdateObject;

static void FusionUpdate_dealloc(PyObject *o)
{
    FusionUpdateObject *self = (FusionUpdateObject *)o;
    int i;
    for (i = 0; i < 4; ++i)
        Py_CLEAR(self->refs[i]);
    Fu_dealloc(o);
}

static int FusionUpdate_init(FusionUpdateObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"meas", "shadow", "snap", "hist", "n", "m", "H", "R", "y", "dx", "S", "Sinv", "K",
                             "PHt", "T", "TH", "X", "KR", "w", "L", "M", "nis", NULL};
    static const char *names[FUP_NBUF] = {"H", "R", "y", "dx", "S", "Sinv", "K", "PHt", "T", "TH", "X",
                                          "KR", "w", "L", "M", "nis"};
    /* H R y dx S Sinv K PHt T TH X KR w L M nis: 0 n n, 1 n m, 2 m m, 3 m, 4 n, 5 one */
    static const int kind[FUP_NBUF] = {1, 2, 3, 4, 2, 2, 1, 1, 0, 1, 0, 1, 3, 2, 2, 5};
    int wr[FUP_NBUF];
    PyObject *o[FUP_NBUF], *meas, *sh, *sn, *hist;
    Py_ssize_t len[FUP_NBUF];
    void *ptr[FUP_NBUF];
    double *kb[15];
    FusionMeasObject *mo;
    FusStateObject *so, *no;
    HistCopyObject *ho;
    int n, m, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOiiOOOOOOOOOOOOOOOO", kwlist, &meas, &sh, &sn, &hist, &n, &m,
                                     &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10],
                                     &o[11], &o[12], &o[13], &o[14], &o[15]))
        return -1;
    if (fu_check_unbound(&self->b, "FusionUpdate") < 0)
        return -1;
    if (!PyObject_TypeCheck(meas, &FusionMeasType) || !PyObject_TypeCheck(sh, &FusStateType) ||
        !PyObject_TypeCheck(sn, &FusStateType) || !PyObject_TypeCheck(hist, &HistCopyType)) {
        PyErr_SetString(PyExc_TypeError, "FusionUpdate: a FusionMeas, two FusState and a HistCopy");
        return -1;
    }
    mo = (FusionMeasObject *)meas;
    so = (FusStateObject *)sh;
    no = (FusStateObject *)sn;
    ho = (HistCopyObject *)hist;
    if (fu_check_bound(&mo->b, "FusionMeas") < 0 || fu_check_bound(&so->b, "FusState") < 0 ||
        fu_check_bound(&no->b, "FusState") < 0 || fu_check_bound(&ho->b, "HistCopy") < 0)
        return -1;
    if (so->s.n != n || no->s.n != n || mo->m.n != n || mo->P != so->s.P || mo->p != so->s.p ||
        mo->Th != so->s.Th || m < 1 || m > 64) {
        PyErr_SetString(PyExc_ValueError, "FusionUpdate: the measurement model bound to the shadow state, "
                                          "states of n rows, m in 1..64");
        return -1;
    }
    for (i = 0; i < FUP_NBUF; ++i) {
        Py_ssize_t nn = (Py_ssize_t)n * n, nm = (Py_ssize_t)n * m, mm = (Py_ssize_t)m * m;
        len[i] = kind[i] == 0 ? nn : kind[i] == 1 ? nm : kind[i] == 2 ? mm : kind[i] == 3 ? m : kind[i] == 4 ? n : 1;
        wr[i] = i >= 3;
    }
    if (fu_bind(FUP_NBUF, o, len, wr, NULL, names, self->b.views, ptr) < 0)
        return -1;
    self->b.nviews = FUP_NBUF;
    if (ptr[2] != (void *)mo->y) {
        PyErr_SetString(PyExc_ValueError, "FusionUpdate: the measurement model writes another y");
        return -1;                      /* (the bound views are released by the deallocation) */
    }
    for (i = 0; i < 15; ++i)
        kb[i] = ptr[i];
    ct_kalman_bind(&self->u, n, m, kb);
    self->nis = ptr[15];
    self->f.m = &mo->m;
    self->f.xi_model = mo->xi_model;
    self->f.Phi = mo->Phi;
    self->f.Xi = mo->Xi;
    self->f.XiP = mo->XiP;
    self->f.y = mo->y;
    self->f.Psi = mo->Psi;
    self->f.shadow = &so->s;
    self->f.snap = &no->s;
    self->f.live_t = ho->lt;
    self->f.live_d = ho->ld;
    self->f.live_hc = ho->lhc;
    self->f.shadow_t = ho->st;
    self->f.shadow_d = ho->sd;
    self->f.shadow_hc = ho->shc;
    self->f.hist_cap = ho->cap;
    self->f.hist_mark = ho->mark;
    self->refs[0] = meas;
    self->refs[1] = sh;
    self->refs[2] = sn;
    self->refs[3] = hist;
    for (i = 0; i < 4; ++i)
        Py_INCREF(self->refs[i]);
    return 0;
}

/* prepare(t_ref, q, R_ms, C): FusionFilter._restore */
static PyObject *FusionUpdate_prepare(FusionUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double q[3], R[9], C[36];
    int64_t t;
    if (fu_check_bound(&self->b, "FusionUpdate") < 0 || ct_py_nargs("prepare", nargs, 4) < 0 ||
        ct_py_int64(args[0], &t) < 0 || !hist_ok(self->f.live_hc, self->f.hist_cap) ||
        !hist_ok(self->f.shadow_hc, self->f.hist_cap) || !mark_ok(self->f.hist_mark, self->f.hist_cap))
        return NULL;
    if (fu_small(args[1], 3, q, "q") < 0 || fu_small(args[2], 9, R, "R_ms") < 0 || fu_small(args[3], 36, C, "C") < 0)
        return NULL;
    ct_fusion_prepare(&self->f, t, q, R, C);
    Py_RETURN_NONE;
}

/* update(gate, sym) -> flags: FusionFilter._update_shadow (the NIS into the bound nis) */
static PyObject *FusionUpdate_update(FusionUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double gate;
    int sym;
    if (fu_check_bound(&self->b, "FusionUpdate") < 0 || ct_py_nargs("update", nargs, 2) < 0 ||
        ct_py_double(args[0], &gate) < 0)
        return NULL;
    sym = PyObject_IsTrue(args[1]);
    if (sym < 0)
        return NULL;
    return PyLong_FromLong(ct_fusion_update(&self->u, self->f.shadow, gate, sym, self->nis));
}

static PyMethodDef FusionUpdate_methods[] = {
    {"prepare", (PyCFunction)(void (*)(void))FusionUpdate_prepare, METH_FASTCALL,
     "prepare(t_ref, q, R_ms, C): the shadow restored from the snapshot, its history rewound, the measurement "
     "evaluated"},
    {"update", (PyCFunction)(void (*)(void))FusionUpdate_update, METH_FASTCALL,
     "update(gate, sym) -> flags: the Kalman update of the shadow, accepted: symmetrised when sym, corrected"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FusionUpdateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FusionUpdate",
    .tp_basicsize = sizeof(FusionUpdateObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FusionUpdate(meas, shadow, snap, hist, n, m, H, R, y, dx, S, Sinv, K, PHt, T, TH, X, KR, w, L, M, "
              "nis): the fusion filter's delayed update, its restore and its Kalman update in one call each",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FusionUpdate_init,
    .tp_dealloc = FusionUpdate_dealloc,
    .tp_methods = FusionUpdate_methods,
};

/* ---------------------------------------------------------------- registration */
int ct_register_fusion(PyObject *m)
{
    static const struct { const char *name; long v; } consts[] = {
        {"RIO_T", CT_RIO_T}, {"RIO_IMU_FIRST", CT_RIO_IMU_FIRST}, {"RIO_IMU_COUNT", CT_RIO_IMU_COUNT},
        {"RIO_HIST_FIRST", CT_RIO_HIST_FIRST}, {"RIO_HIST_COUNT", CT_RIO_HIST_COUNT},
        {"RIO_HIST_PUSHED", CT_RIO_HIST_PUSHED}, {"RIO_SNAP_PENDING", CT_RIO_SNAP_PENDING},
        {"RIO_SNAP_T", CT_RIO_SNAP_T}, {"RIO_UNITS", CT_RIO_UNITS}, {"RIO_PRED_COUNT", CT_RIO_PRED_COUNT},
        {"RIO_STEPS", CT_RIO_STEPS}, {"RIO_SPLIT", CT_RIO_SPLIT}, {"RIO_N", CT_RIO_N},
        {"RFO_DT_LAST", CT_RFO_DT_LAST}, {"RFO_KA", CT_RFO_KA}, {"RFO_KG", CT_RFO_KG}, {"RFO_N", CT_RFO_N},
        {"REPLAY_CAUGHT_UP", CT_REPLAY_CAUGHT_UP}, {"REPLAY_BUDGET", CT_REPLAY_BUDGET},
        {"REPLAY_LOST", CT_REPLAY_LOST}, {"REPLAY_SNAPSHOT", CT_REPLAY_SNAPSHOT},
        {"IMU_WIDTH", CT_IMU_WIDTH}, {"IMU_F", CT_IMU_F}, {"IMU_W", CT_IMU_W}, {"IMU_FSRC", CT_IMU_FSRC},
        {"IMU_PHI", CT_IMU_PHI}, {"HIST_WIDTH", CT_HIST_WIDTH}, {"HIST_P", CT_HIST_P}, {"HIST_R", CT_HIST_R},
        {"HMK_VALID", CT_HMK_VALID}, {"HMK_LIVE_SLOT", CT_HMK_LIVE_SLOT}, {"HMK_LIVE_T", CT_HMK_LIVE_T},
        {"HMK_SHADOW_SLOT", CT_HMK_SHADOW_SLOT}, {"HMK_SHADOW_T", CT_HMK_SHADOW_T}, {"HMK_N", CT_HMK_N}};
    size_t i;
    if (ct_py_add_type(m, &FusionMeasType, "FusionMeas") < 0 || ct_py_add_type(m, &FusStateType, "FusState") < 0 ||
        ct_py_add_type(m, &ReplayType, "Replay") < 0 || ct_py_add_type(m, &SnapAuxType, "SnapAux") < 0 ||
        ct_py_add_type(m, &PoseAtType, "PoseAt") < 0 || ct_py_add_type(m, &MotionCovType, "MotionCov") < 0 ||
        ct_py_add_type(m, &CompensateType, "Compensate") < 0 || ct_py_add_type(m, &HistCopyType, "HistCopy") < 0 ||
        ct_py_add_type(m, &FusionUpdateType, "FusionUpdate") < 0)
        return -1;
    for (i = 0; i < sizeof consts / sizeof consts[0]; ++i)
        if (PyModule_AddIntConstant(m, consts[i].name, consts[i].v) < 0)
            return -1;
    return 0;
}
