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
#include "py_solve.h"
#include "py_pulse.h"

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

/* ---------------------------------------------------------------- SolveStart */
/* per channel: var, sig, S (3n), the history's t (cap), d (cap x width), hc (2), the sensor's tr (1),
 * its filter's fs, the tracked pose's position, rotation, warm_p, warm_R, hemisphere */
#define SS_NB 13
#define SS_MAXCH 16
static const char *ss_names[SS_NB] = {"var", "sig", "S", "hist_t", "hist_d", "hc", "tr", "fs", "position",
                                      "rotation", "warm_p", "warm_R", "hemisphere"};
static const int ss_wr[SS_NB] = {0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 0};
static const int ss_i64[SS_NB] = {0, 0, 0, 1, 0, 1, 1, 1, 0, 0, 0, 0, 0};

typedef struct {
    const double *var, *S, *tp, *tR, *hemi;
    double *sig, *wp, *wR;
    struct ct_hist h;
    const int64_t *tr, *fs;
} ss_channel;

typedef struct {
    PyObject_HEAD
    PyObject *run;               /* the SolveRun whose solve this begins (held) */
    const struct ct_solve *s;
    int n, nch, fs_init, range_check;
    double floor2, range_m;
    const double *cur;
    ss_channel ch[SS_MAXCH];
    Py_buffer views[SS_MAXCH * SS_NB + 1];
    int nviews;
} SolveStartObject;

/* channel k's history head and count in range; else ValueError "<who>: the history's ..." and -1 */
static int ss_hist_ok(const ss_channel *c, const char *who)
{
    if (c->h.hc[0] < 0 || c->h.hc[0] >= c->h.cap || c->h.hc[1] < 0 || c->h.hc[1] > c->h.cap) {
        PyErr_Format(PyExc_ValueError, "%s: the history's head or count out of range", who);
        return -1;
    }
    return 0;
}

/* ct_ahead_inputs on channel c of s against the solve ahead ah (AheadStart.inputs, HandOver.begin) */
static int ss_ahead_inputs(const SolveStartObject *s, const ss_channel *c, int have, const struct ct_ahead_buf *ah)
{
    return ct_ahead_inputs(s->n, c->var, c->sig, s->floor2, &c->h, c->tr[0], have, c->fs[s->fs_init] != 0,
                           s->range_m, c->tp, c->tR, c->wp, c->wR, c->hemi, c->S, s->cur, ah);
}

static void SolveStart_dealloc(SolveStartObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    Py_XDECREF(self->run);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ss_bind(SolveStartObject *self, PyObject *o, Py_ssize_t len, int k, void **ptr)
{
    Py_buffer *v = &self->views[self->nviews];
    if (ct_py_buffer(o, len, 8, ss_i64[k] ? "ql" : "d", ss_wr[k], v, ss_names[k]) < 0)
        return -1;
    self->nviews++;
    *ptr = v->buf;
    return 0;
}

/* SolveStart(run, n, floor2, range_m, fs_init, fs_n, currents, channels, warm_ac=False): channels a sequence of
 * SS_NB buffers per channel (ss_names); warm_ac: the warm start without the range check (ACFusionTracker's) */
static int SolveStart_init(SolveStartObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"run", "n", "floor2", "range_m", "fs_init", "fs_n", "currents", "channels", "warm_ac",
                             NULL};
    PyObject *run, *cur, *chans, *seq = NULL, *one = NULL;
    int n, fs_init, fs_n, k, i, warm_ac = 0;
    double floor2, range_m;
    void *p;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OiddiiOO|p", kwlist, &run, &n, &floor2, &range_m, &fs_init, &fs_n,
                                     &cur, &chans, &warm_ac))
        return -1;
    if (self->run != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "SolveStart: already bound");
        return -1;
    }
    self->s = ct_py_solve_of(run);
    if (self->s == NULL)
        return -1;
    if (n != self->s->n || fs_init < 0 || fs_init >= fs_n) {
        PyErr_SetString(PyExc_ValueError, "SolveStart: the coil count differs from the solve's, or a bad flag index");
        return -1;
    }
    if (ss_bind(self, cur, n, 0, &p) < 0)          /* (the currents: read, float64) */
        return -1;
    self->cur = p;
    seq = PySequence_Fast(chans, "SolveStart: channels must be a sequence");
    if (seq == NULL)
        goto fail;
    self->nch = (int)PySequence_Fast_GET_SIZE(seq);
    if (self->nch < 1 || self->nch > SS_MAXCH) {
        PyErr_Format(PyExc_ValueError, "SolveStart: 1..%d channels", SS_MAXCH);
        goto fail;
    }
    for (i = 0; i < self->nch; ++i) {
        ss_channel *c = &self->ch[i];
        void *ptr[SS_NB];
        Py_ssize_t len[SS_NB] = {3 * n, 3 * n, 3 * n, 2, 0, 2, 1, fs_n, 3, 9, 3, 9, 3};
        one = PySequence_Fast(PySequence_Fast_GET_ITEM(seq, i), "SolveStart: a channel must be a sequence");
        if (one == NULL)
            goto fail;
        if (PySequence_Fast_GET_SIZE(one) != SS_NB) {
            PyErr_Format(PyExc_ValueError, "SolveStart: a channel needs %d buffers", SS_NB);
            goto fail;
        }
        for (k = 0; k < SS_NB; ++k) {
            if (k == 4)
                len[4] = (Py_ssize_t)c->h.cap * CT_HIST_WIDTH;
            if (ss_bind(self, PySequence_Fast_GET_ITEM(one, k), len[k], k, &ptr[k]) < 0)
                goto fail;
            if (k == 3)
                c->h.cap = (int64_t)(self->views[self->nviews - 1].len / 8);
        }
        Py_CLEAR(one);
        c->var = ptr[0];
        c->sig = ptr[1];
        c->S = ptr[2];
        c->h.t = ptr[3];
        c->h.d = ptr[4];
        c->h.hc = ptr[5];
        c->tr = ptr[6];
        c->fs = ptr[7];
        c->tp = ptr[8];
        c->tR = ptr[9];
        c->wp = ptr[10];
        c->wR = ptr[11];
        c->hemi = ptr[12];
    }
    Py_DECREF(seq);
    self->n = n;
    self->floor2 = floor2;
    self->range_m = range_m;
    self->range_check = !warm_ac;
    self->fs_init = fs_init;
    Py_INCREF(run);
    self->run = run;
    return 0;
fail:
    Py_XDECREF(one);
    Py_XDECREF(seq);
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    return -1;
}

/* start(k, have_pose) -> status | warm << 8 (ct_solve_start on channel k) */
static PyObject *SolveStart_start(SolveStartObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    int have, warm = 0, st;
    const ss_channel *c;
    if (self->run == NULL || ct_py_nargs("start", nargs, 2) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    if (have < 0)
        return NULL;
    if (k < 0 || k >= self->nch) {
        PyErr_SetString(PyExc_IndexError, "SolveStart.start: channel out of range");
        return NULL;
    }
    c = &self->ch[k];
    if (ss_hist_ok(c, "SolveStart.start") < 0)
        return NULL;
    st = ct_solve_start(self->s, self->n, c->var, c->sig, self->floor2, &c->h, c->tr[0], have,
                        c->fs[self->fs_init] != 0, self->range_m, c->tp, c->tR, c->wp, c->wR, c->hemi, c->S,
                        self->cur, self->range_check, &warm);
    return PyLong_FromLong(st | (warm << 8));
}

static PyMethodDef SolveStart_methods[] = {
    {"start", (PyCFunction)(void (*)(void))SolveStart_start, METH_FASTCALL,
     "start(k, have_pose) -> status | warm << 8: channel k's sigma, warm start and solve's begin"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SolveStartType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SolveStart",
    .tp_basicsize = sizeof(SolveStartObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SolveStart(run, n, floor2, range_m, fs_init, fs_n, currents, channels, warm_ac=False): the fused "
              "tracker's start of a burst's solve (sigma, warm start, begin) bound to its channels' and filters' "
              "buffers; warm_ac: the AC tracker's warm start (no range check)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SolveStart_init,
    .tp_dealloc = (destructor)SolveStart_dealloc,
    .tp_methods = SolveStart_methods,
};

/* ---------------------------------------------------------------- AheadStart */
/* per channel: its PulseWindow, its ring's hc (head, count, ...), then its _Ahead's S, sigma (3n),
 * currents (n), hemisphere (3), warm_p (3), warm_R (9), amp (3), var (3) and wst (int64, 1) */
#define AS_NB 10
static const char *as_names[AS_NB] = {"hc", "S", "sigma", "currents", "hemisphere", "warm_p", "warm_R", "amp",
                                      "var", "wst"};
#define AS_FAR ((int64_t)1 << 61)     /* measure/pulse.py _T_FAR: a time beyond goes to the reference */
#define AS_ASK (-3)

typedef struct {
    const struct ct_pulse *x;
    const struct ct_sample_ring *r;
    double *res;
    int64_t *ires;
    const int64_t *hc;
    struct ct_ahead_buf ah;
} as_channel;

typedef struct {
    PyObject_HEAD
    SolveStartObject *ss;        /* the channels' inputs, filters and tracked poses, and the solve (held) */
    PyObject *windows;           /* the channels' PulseWindows (a tuple, held) */
    const double *measured, *nominal;
    as_channel ch[SS_MAXCH];
    Py_buffer views[SS_MAXCH * AS_NB + 2];
    int nviews;
} AheadStartObject;

static void AheadStart_dealloc(AheadStartObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    Py_XDECREF(self->ss);
    Py_XDECREF(self->windows);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int as_bind(AheadStartObject *self, PyObject *o, Py_ssize_t len, const char *fmt, int wr, const char *name,
                   void **ptr)
{
    Py_buffer *v = &self->views[self->nviews];
    if (ct_py_buffer(o, len, 8, fmt, wr, v, name) < 0)
        return -1;
    self->nviews++;
    *ptr = v->buf;
    return 0;
}

static int as_channel_bind(AheadStartObject *self, as_channel *c, PyObject *one, int n)
{
    void *ptr[AS_NB];
    const Py_ssize_t len[AS_NB] = {2, 3 * n, 3 * n, n, 3, 3, 9, 3, 3, 1};
    int k;
    if (PySequence_Fast_GET_SIZE(one) != AS_NB + 1) {
        PyErr_Format(PyExc_ValueError, "AheadStart: a channel needs a PulseWindow and %d buffers", AS_NB);
        return -1;
    }
    if (ct_py_pulse_window_of(PySequence_Fast_GET_ITEM(one, 0), &c->x, &c->r, &c->res, &c->ires) < 0)
        return -1;
    for (k = 0; k < AS_NB; ++k)
        if (as_bind(self, PySequence_Fast_GET_ITEM(one, k + 1), len[k], k && k < AS_NB - 1 ? "d" : "ql", k > 0,
                    as_names[k], &ptr[k]) < 0)
            return -1;
    c->hc = ptr[0];
    c->ah.S = ptr[1];
    c->ah.sigma = ptr[2];
    c->ah.cur = ptr[3];
    c->ah.hemi = ptr[4];
    c->ah.wp = ptr[5];
    c->ah.wR = ptr[6];
    c->ah.amp = ptr[7];
    c->ah.var = ptr[8];
    c->ah.warm = ptr[9];
    return 0;
}

/* AheadStart(start, measured, nominal, channels): start the tracker's bound SolveStart, measured and
 * nominal the schedule's currents (float64, n), channels per channel of start's (PulseWindow, hc, S,
 * sigma, currents, hemisphere, warm_p, warm_R, amp, var, wst) */
static int AheadStart_init(AheadStartObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"start", "measured", "nominal", "channels", NULL};
    PyObject *ss, *measured, *nominal, *chans, *seq = NULL, *one = NULL, *wins = NULL;
    SolveStartObject *s;
    void *p;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!OOO", kwlist, &SolveStartType, &ss, &measured, &nominal, &chans))
        return -1;
    s = (SolveStartObject *)ss;
    if (self->ss != NULL || s->run == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "AheadStart: already bound, or the SolveStart is not");
        return -1;
    }
    if (as_bind(self, measured, s->n, "d", 0, "measured", &p) < 0)
        return -1;
    self->measured = p;
    if (as_bind(self, nominal, s->n, "d", 0, "nominal", &p) < 0)
        goto fail;
    self->nominal = p;
    seq = PySequence_Fast(chans, "AheadStart: channels must be a sequence");
    if (seq == NULL)
        goto fail;
    if (PySequence_Fast_GET_SIZE(seq) != s->nch) {
        PyErr_SetString(PyExc_ValueError, "AheadStart: one entry per channel of the SolveStart");
        goto fail;
    }
    wins = PyTuple_New(s->nch);
    if (wins == NULL)
        goto fail;
    for (i = 0; i < s->nch; ++i) {
        one = PySequence_Fast(PySequence_Fast_GET_ITEM(seq, i), "AheadStart: a channel must be a sequence");
        if (one == NULL || as_channel_bind(self, &self->ch[i], one, s->n) < 0)
            goto fail;
        Py_INCREF(PySequence_Fast_GET_ITEM(one, 0));
        PyTuple_SET_ITEM(wins, i, PySequence_Fast_GET_ITEM(one, 0));
        Py_CLEAR(one);
    }
    Py_DECREF(seq);
    Py_INCREF(ss);
    self->ss = s;
    self->windows = wins;
    return 0;
fail:
    Py_XDECREF(one);
    Py_XDECREF(seq);
    Py_XDECREF(wins);
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    return -1;
}

/* start(k, have_pose, start_us, end_us) -> status | warm << 8, CT_AHEAD_NO_WINDOW, or AS_ASK for a time
 * the extraction does not take (ct_ahead_start on channel k, its last window [start_us, end_us]) */
static PyObject *AheadStart_start(AheadStartObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k, t0, t1;
    int have;
    const SolveStartObject *s = self->ss;
    const ss_channel *c;
    const as_channel *a;
    struct ct_sample_ring r;
    if (s == NULL || ct_py_nargs("start", nargs, 4) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    if (have < 0)
        return NULL;
    if (k < 0 || k >= s->nch) {
        PyErr_SetString(PyExc_IndexError, "AheadStart.start: channel out of range");
        return NULL;
    }
    if (!ct_py_int_only(args[2], &t0) || !ct_py_int_only(args[3], &t1) ||
        !(-AS_FAR < t0 && t0 < AS_FAR && -AS_FAR < t1 && t1 < AS_FAR))
        return PyLong_FromLong(AS_ASK);
    c = &s->ch[k];
    a = &self->ch[k];
    if (c->h.hc[0] < 0 || c->h.hc[0] >= c->h.cap || c->h.hc[1] < 0 || c->h.hc[1] > c->h.cap ||
        a->hc[0] < 0 || a->hc[0] >= a->r->cap || a->hc[1] < 0 || a->hc[1] > a->r->cap) {
        PyErr_SetString(PyExc_ValueError, "AheadStart.start: a ring's head or count out of range");
        return NULL;
    }
    r = *a->r;
    r.head = a->hc[0];
    r.count = a->hc[1];
    return PyLong_FromLong(ct_ahead_start(s->s, s->n, &c->h, c->tr[0], have, c->fs[s->fs_init] != 0, s->range_m,
                                          c->tp, c->tR, c->wp, c->wR, c->hemi, a->x, &r, t0, t1, a->res, a->ires,
                                          c->S, c->var, s->floor2, self->measured, self->nominal, &a->ah));
}

/* inputs(k, have_pose) -> warm | same << 1 (ct_ahead_inputs on channel k against its solve ahead) */
static PyObject *AheadStart_inputs(AheadStartObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    int have;
    const SolveStartObject *s = self->ss;
    const ss_channel *c;
    if (s == NULL || ct_py_nargs("inputs", nargs, 2) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    if (have < 0)
        return NULL;
    if (k < 0 || k >= s->nch) {
        PyErr_SetString(PyExc_IndexError, "AheadStart.inputs: channel out of range");
        return NULL;
    }
    c = &s->ch[k];
    if (ss_hist_ok(c, "AheadStart.inputs") < 0)
        return NULL;
    return PyLong_FromLong(ss_ahead_inputs(s, c, have, &self->ch[k].ah));
}

static PyMethodDef AheadStart_methods[] = {
    {"inputs", (PyCFunction)(void (*)(void))AheadStart_inputs, METH_FASTCALL,
     "inputs(k, have_pose) -> warm | same << 1: channel k's sigma and warm start, and whether its burst's inputs "
     "are those its solve ahead began with"},
    {"start", (PyCFunction)(void (*)(void))AheadStart_start, METH_FASTCALL,
     "start(k, have_pose, start_us, end_us) -> status | warm << 8, -2 (no window) or -3 (a time for the "
     "reference): channel k's warm start and the begin of its solve ahead on its last window, warm or acquiring"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject AheadStartType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.AheadStart",
    .tp_basicsize = sizeof(AheadStartObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "AheadStart(start, measured, nominal, channels): the fused tracker's begin of a solve ahead (warm "
              "start, the last window's extraction, the copies, begin, warm or acquiring) bound to a SolveStart and "
              "the _Aheads",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)AheadStart_init,
    .tp_dealloc = (destructor)AheadStart_dealloc,
    .tp_methods = AheadStart_methods,
};

/* ------------------------------------------------------------- HandOver */
typedef struct {
    PyObject_HEAD
    AheadStartObject *as;        /* the solves ahead's inputs (and through it the SolveStart), held */
    BurstInputsObject *bi;       /* the channels' window flags and the faults, held */
    PyObject *supo;              /* the supervisor's SupMag, held */
    const struct ct_sup *sup;
    int64_t node[SS_MAXCH];
    int64_t *st;                 /* the tracker's _ahead_st (nch x 2) */
    Py_buffer stv;
    int bound;
} HandOverObject;

static void HandOver_dealloc(HandOverObject *self)
{
    if (self->bound)
        PyBuffer_Release(&self->stv);
    Py_XDECREF(self->as);
    Py_XDECREF(self->bi);
    Py_XDECREF(self->supo);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* HandOver(ahead, inputs, sup, nodes, ahead_st): the tracker's AheadStart and BurstInputs, the
 * supervisor's SupMag, the channels' nodes and the tracker's _ahead_st (int64, nch x 2) */
static int HandOver_init(HandOverObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"ahead", "inputs", "sup", "nodes", "ahead_st", NULL};
    PyObject *as, *bi, *supo, *nodes, *st, *seq;
    const struct ct_sup *sup;
    int nch, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!O!OOO", kwlist, &AheadStartType, &as, &BurstInputsType, &bi, &supo,
                                     &nodes, &st))
        return -1;
    if (self->bound || ((AheadStartObject *)as)->ss == NULL || !((BurstInputsObject *)bi)->nch) {
        PyErr_SetString(PyExc_RuntimeError, "HandOver: already bound, or a part is not");
        return -1;
    }
    nch = ((AheadStartObject *)as)->ss->nch;
    if (((BurstInputsObject *)bi)->nch != nch) {
        PyErr_SetString(PyExc_ValueError, "HandOver: the parts' channels differ");
        return -1;
    }
    sup = ct_py_sup_of(supo);
    if (sup == NULL)
        return -1;
    seq = PySequence_Fast(nodes, "HandOver: nodes must be a sequence");
    if (seq == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(seq) != nch) {
        Py_DECREF(seq);
        PyErr_SetString(PyExc_ValueError, "HandOver: one node per channel");
        return -1;
    }
    for (i = 0; i < nch; ++i)
        if (ct_py_int64(PySequence_Fast_GET_ITEM(seq, i), &self->node[i]) < 0) {
            Py_DECREF(seq);
            return -1;
        }
    Py_DECREF(seq);
    if (ct_py_buffer(st, 2 * nch, 8, "ql", 1, &self->stv, "ahead_st") < 0)
        return -1;
    self->st = self->stv.buf;
    self->sup = sup;
    Py_INCREF(as);
    Py_INCREF(bi);
    Py_INCREF(supo);
    self->as = (AheadStartObject *)as;
    self->bi = (BurstInputsObject *)bi;
    self->supo = supo;
    self->bound = 1;
    return 0;
}

#define HO_NO_BURST ((int64_t)(-9223372036854775807LL - 1))    /* track/magnetic.py NO_BURST */

/* begin(k, have_pose, burst, running) -> bits | veto << 32 | unusable << 33 | code << 34: channel k's
 * ct_handover_status; where usable and not vetoed (code > 0) the test for its solve ahead of burst
 * (ct_handover_ahead; code 1: none to take over), and where it passes AheadStart.inputs (ct_ahead_inputs)
 * and _Ahead.release (code 2: another start or other inputs, the turn acquiring; 3: the same, the turn
 * warm; 4: the same start and inputs) */
static PyObject *HandOver_begin(HandOverObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k, burst, running, r;
    int have, w;
    const BurstInputsObject *bi = self->bi;
    const SolveStartObject *s;
    const ss_channel *c;
    if (!self->bound || ct_py_nargs("begin", nargs, 4) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    if (have < 0 || ct_py_int64(args[2], &burst) < 0 || ct_py_int64(args[3], &running) < 0)
        return NULL;
    s = self->as->ss;
    if (k < 0 || k >= s->nch) {
        PyErr_SetString(PyExc_IndexError, "HandOver.begin: channel out of range");
        return NULL;
    }
    r = ct_handover_status(&bi->b, bi->fl[k], bi->nf, bi->fv, bi->nc, self->sup, self->node[k]);
    if (r < 0) {
        PyErr_SetString(PyExc_ValueError, "HandOver.begin: bits or flags out of range");
        return NULL;
    }
    if (r >> 32)
        return PyLong_FromLongLong(r);
    if (!ct_handover_ahead(&self->st[2 * k], burst, running, k))
        return PyLong_FromLongLong(r | (int64_t)1 << 34);
    c = &s->ch[k];
    if (ss_hist_ok(c, "HandOver.begin") < 0)
        return NULL;
    w = ss_ahead_inputs(s, c, have, &self->as->ch[k].ah);
    self->st[2 * k] = HO_NO_BURST;
    return PyLong_FromLongLong(r | (int64_t)(w & 2 ? 4 : 2 + (w & 1)) << 34);
}

static PyMethodDef HandOver_methods[] = {
    {"begin", (PyCFunction)(void (*)(void))HandOver_begin, METH_FASTCALL,
     "begin(k, have_pose, burst, running) -> bits | veto << 32 | unusable << 33 | code << 34: MagneticTracker."
     "_begin_handover's compiled steps (code 0: unusable or vetoed, 1: no solve ahead to take over, 2: a solve "
     "ahead from another start or on other inputs, released, the turn acquiring, 3: the same, the turn warm, 4: "
     "from the same start on the same inputs, released)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject HandOverType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.HandOver",
    .tp_basicsize = sizeof(HandOverObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "HandOver(ahead, inputs, sup, nodes, ahead_st): a burst's begin in the fused tracker's hand-over "
              "(its status, the supervisor's pose status, the take-over of its solve ahead) in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)HandOver_init,
    .tp_dealloc = (destructor)HandOver_dealloc,
    .tp_methods = HandOver_methods,
};

int ct_register_begin(PyObject *m)
{
    if (ct_py_add_type(m, &BurstInputsType, "BurstInputs") < 0)
        return -1;
    if (ct_py_add_type(m, &SolveStartType, "SolveStart") < 0)
        return -1;
    if (ct_py_add_type(m, &AheadStartType, "AheadStart") < 0)
        return -1;
    return ct_py_add_type(m, &HandOverType, "HandOver");
}
