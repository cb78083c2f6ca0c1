/*
 * CPython glue of a solved burst's report (src/report.c): the type ReportChain, bound once
 * (start-up) to one channel's and the tracker's numpy arrays; its per-call method (METH_FASTCALL)
 * takes numbers only, writes into the bound buffers and creates no Python object (the small ints
 * it returns are the interpreter's cached ones).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* the bound buffers, in the constructor's order */
enum { RC_CENTERS, RC_PREV, RC_H, RC_U, RC_G, RC_DX, RC_D, RC_XD, RC_MOTION, RC_SP, RC_SR, RC_SCOV, RC_TP, RC_TR,
       RC_S, RC_SIGMA, RC_START, RC_END, RC_Q, RC_WL, RC_V, RC_COV, RC_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_quality qs;
    struct ct_report r;
    Py_buffer views[RC_NBUF];
    int held[RC_NBUF];
    int bound;
    /* the quiet term's magnetometer ring (bind_quiet): head and count, samples, its constants */
    Py_buffer qhc, qb;
    int quiet;
    int64_t qcap;
    double earth, quiet_sigma;
} ReportChainObject;

static void rc_release(ReportChainObject *self)
{
    int i;
    for (i = 0; i < RC_NBUF; ++i)
        if (self->held[i]) {
            PyBuffer_Release(&self->views[i]);
            self->held[i] = 0;
        }
    if (self->quiet) {
        PyBuffer_Release(&self->qhc);
        PyBuffer_Release(&self->qb);
        self->quiet = 0;
    }
}

static void ReportChain_dealloc(ReportChainObject *self)
{
    rc_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ReportChain_init(ReportChainObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "dof", "scale", "max_gap_us", "row", "centers", "prev", "H", "u", "g", "dx", "d",
                             "xd", "motion", "sp", "sR", "scov", "tp", "tR", "S", "sigma", "start", "end", "q", "wl",
                             "v", "cov", "rms_s", "motion_coils", NULL};
    static const char *names[RC_NBUF] = {"centers", "prev", "H", "u", "g", "dx", "d", "xd", "motion", "sp", "sR",
                                         "scov", "tp", "tR", "S", "sigma", "start", "end", "q", "wl", "v", "cov"};
    static const int writable[RC_NBUF] = {0, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 1, 1, 0, 0, 0, 0, 1, 0, 0, 1};
    PyObject *o[RC_NBUF];
    Py_ssize_t len[RC_NBUF];
    void *ptr[RC_NBUF];
    double scale, gap, rms_s = 0.0;
    Py_ssize_t row;
    int n, dof, i, motion, mcoils = -1;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiddnOOOOOOOOOOOOOOOOOOOOOO|di", kwlist, &n, &dof, &scale, &gap, &row,
                                     &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10],
                                     &o[11], &o[12], &o[13], &o[14], &o[15], &o[16], &o[17], &o[18], &o[19], &o[20],
                                     &o[21], &rms_s, &mcoils))
        return -1;
    if (mcoils != -1 && mcoils != 0 && mcoils != n) {
        PyErr_Format(PyExc_ValueError, "ReportChain: motion_coils must be 0 (no motion term) or n, got %d", mcoils);
        return -1;
    }
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ReportChain: already bound");
        return -1;
    }
    if (n < 2 || n > 4096) {
        PyErr_Format(PyExc_ValueError, "ReportChain: n must be in 2..4096, got %d", n);
        return -1;
    }
    motion = o[RC_WL] != Py_None;
    if (motion != (o[RC_V] != Py_None) || motion != (o[RC_COV] != Py_None)) {
        PyErr_SetString(PyExc_TypeError, "ReportChain: wl, v and cov are given together or not at all");
        return -1;
    }
    len[RC_CENTERS] = 3 * n;
    len[RC_PREV] = 14 * (row + 1);
    len[RC_H] = 18 * n;
    len[RC_U] = 3 * n;
    len[RC_G] = len[RC_DX] = len[RC_XD] = 6;
    len[RC_D] = n;
    len[RC_MOTION] = 2;
    len[RC_SP] = len[RC_TP] = len[RC_WL] = len[RC_V] = 3;
    len[RC_SR] = len[RC_TR] = 9;
    len[RC_SCOV] = len[RC_COV] = 36;
    len[RC_S] = len[RC_SIGMA] = 3 * n;
    len[RC_START] = len[RC_END] = n;
    len[RC_Q] = 4;
    if (row < 0) {
        PyErr_SetString(PyExc_ValueError, "ReportChain: row must be >= 0");
        return -1;
    }
    memset(self->held, 0, sizeof self->held);
    for (i = 0; i < RC_NBUF; ++i) {
        int ints = i == RC_START || i == RC_END;
        ptr[i] = NULL;
        if (o[i] == Py_None && (i == RC_WL || i == RC_V || i == RC_COV))
            continue;
        if (ct_py_buffer(o[i], len[i], 8, ints ? "ql" : "d", writable[i], &self->views[i], names[i]) < 0) {
            rc_release(self);
            return -1;
        }
        self->held[i] = 1;
        if (i != RC_PREV && self->views[i].len != len[i] * 8) {
            PyErr_Format(PyExc_TypeError, "%s: needs %zd items", names[i], len[i]);
            rc_release(self);
            return -1;
        }
        ptr[i] = self->views[i].buf;
    }
    self->qs.n = mcoils == 0 ? 0 : n;   /* 0: PoseQuality.grade_burst without the motion term (its _n 0) */
    self->qs.dof = dof;
    self->qs.scale = scale;
    self->qs.max_gap_us = gap;
    self->qs.centers = ptr[RC_CENTERS];
    self->qs.H = ptr[RC_H];
    self->qs.u = ptr[RC_U];
    self->qs.g = ptr[RC_G];
    self->qs.dx = ptr[RC_DX];
    self->qs.d = ptr[RC_D];
    self->qs.xd = ptr[RC_XD];
    self->r.qs = &self->qs;
    self->r.prev = (double *)ptr[RC_PREV] + 14 * row;
    self->r.motion = ptr[RC_MOTION];
    self->r.sp = ptr[RC_SP];
    self->r.sR = ptr[RC_SR];
    self->r.scov = ptr[RC_SCOV];
    self->r.tp = ptr[RC_TP];
    self->r.tR = ptr[RC_TR];
    self->r.S = ptr[RC_S];
    self->r.sigma = ptr[RC_SIGMA];
    self->r.start = ptr[RC_START];
    self->r.end = ptr[RC_END];
    self->r.q = ptr[RC_Q];
    self->r.wl = ptr[RC_WL];
    self->r.v = ptr[RC_V];
    self->r.cov = ptr[RC_COV];
    self->r.rms_s = rms_s;
    self->bound = 1;
    return 0;
}

/* solved(t_us, cost, nis, quiet, range_m, initialized) -> -1 (beyond range_m) or the quality */
static PyObject *ReportChain_solved(ReportChainObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t_us;
    double cost, nis, quiet, range_m;
    int init;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ReportChain: not bound");
        return NULL;
    }
    if (ct_py_nargs("ReportChain.solved", nargs, 6) < 0)
        return NULL;
    if (ct_py_int64(args[0], &t_us) < 0 || ct_py_double(args[1], &cost) < 0 || ct_py_double(args[2], &nis) < 0 ||
        ct_py_double(args[3], &quiet) < 0 || ct_py_double(args[4], &range_m) < 0)
        return NULL;
    init = PyObject_IsTrue(args[5]);
    if (init < 0)
        return NULL;
    return PyLong_FromLong(ct_report_solved(&self->r, t_us, cost, nis, quiet, range_m, init));
}

/* bind_quiet(hc, b, earth, quiet_sigma): the channel's magnetometer ring (hc int64 (>= 2,): head, count;
 * b float64 (cap, 3)) whose newest sample report() reads for PoseQuality.quiet_term; once */
static PyObject *ReportChain_bind_quiet(ReportChainObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double earth, qs;
    if (!self->bound || self->quiet) {
        PyErr_SetString(PyExc_RuntimeError, "ReportChain.bind_quiet: not bound, or a ring bound already");
        return NULL;
    }
    if (ct_py_nargs("ReportChain.bind_quiet", nargs, 4) < 0 || ct_py_double(args[2], &earth) < 0 ||
        ct_py_double(args[3], &qs) < 0)
        return NULL;
    if (ct_py_buffer(args[0], 2, 8, "ql", 0, &self->qhc, "hc") < 0)
        return NULL;
    if (ct_py_buffer(args[1], 3, 8, "d", 0, &self->qb, "b") < 0) {
        PyBuffer_Release(&self->qhc);
        return NULL;
    }
    if (self->qb.len % 24 != 0) {
        PyBuffer_Release(&self->qhc);
        PyBuffer_Release(&self->qb);
        PyErr_SetString(PyExc_TypeError, "b: needs (capacity, 3) float64 items");
        return NULL;
    }
    self->qcap = (int64_t)(self->qb.len / 24);
    self->earth = earth;
    self->quiet_sigma = qs;
    self->quiet = 1;
    Py_RETURN_NONE;
}

/* report(t_us, cost, nis, range_m, initialized) -> -1 or the quality: solved() with the quiet term read
 * from the ring bind_quiet bound (ct_report_quiet; 0.0 without one: PoseQuality.quiet_term's 0) */
static PyObject *ReportChain_report(ReportChainObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t_us;
    double cost, nis, quiet = 0.0, range_m;
    int init;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ReportChain: not bound");
        return NULL;
    }
    if (ct_py_nargs("ReportChain.report", nargs, 5) < 0)
        return NULL;
    if (ct_py_int64(args[0], &t_us) < 0 || ct_py_double(args[1], &cost) < 0 || ct_py_double(args[2], &nis) < 0 ||
        ct_py_double(args[3], &range_m) < 0)
        return NULL;
    init = PyObject_IsTrue(args[4]);
    if (init < 0)
        return NULL;
    if (self->quiet)
        quiet = ct_report_quiet(self->qhc.buf, self->qb.buf, self->qcap, self->earth, self->quiet_sigma);
    return PyLong_FromLong(ct_report_solved(&self->r, t_us, cost, nis, quiet, range_m, init));
}

/* The POSE frame of the last report into out (send()'s; args: seq, src, node, t_us, status, quality):
 * Transmitter.pose_cov6 on the compiled core with the tracked position, the quaternion and the reported
 * covariance (the motion's where bound, else the solver's); its length, -1 where the wire format refuses
 * a value (as core.pose_frame), -2 with an exception set */
static int rc_frame(ReportChainObject *self, PyObject *const *args, uint8_t *out)
{
    long long ints[3];
    unsigned long long t_us;
    int seq, src;
    static const int int_at[3] = {2, 4, 5};
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ReportChain: not bound");
        return -2;
    }
    seq = (int)PyLong_AsLong(args[0]);
    src = (int)PyLong_AsLong(args[1]);
    if (PyErr_Occurred())
        return -2;
    if (ct_py_pose_ints(args, int_at, ints, &t_us))
        return -1;
    return ct_report_frame(out, seq, src, ints[0], (uint64_t)t_us, self->r.tp, self->r.q,
                           self->r.wl != NULL ? self->r.cov : self->r.scov, ints[1], ints[2]);
}

/* send(write, seq, src, node, t_us, status, quality) -> errors << 8 | the next seq: rc_frame's POSE frame
 * numbered seq and handed to write (the port's) as transmit.Transmitter._write_numbered writes it (a frame
 * the wire format refuses: not sent, seq kept, one error; an Exception write raises: one error) */
static PyObject *ReportChain_send(ReportChainObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_POSE_FRAME_MAX];
    int64_t seq, errors = 0;
    int k;
    if (ct_py_nargs("ReportChain.send", nargs, 7) < 0)
        return NULL;
    k = rc_frame(self, args + 1, out);
    if (k == -2 || ct_py_int64(args[1], &seq) < 0)
        return NULL;
    if (ct_py_write_numbered(args[0], out, k, &seq, &errors) < 0)
        return NULL;
    return PyLong_FromLongLong((long long)((errors << 8) | (seq & 0xFF)));
}

static PyMethodDef ReportChain_methods[] = {
    {"bind_quiet", (PyCFunction)(void (*)(void))ReportChain_bind_quiet, METH_FASTCALL,
     "bind_quiet(hc, b, earth, quiet_sigma): the magnetometer ring whose newest sample report() reads for the "
     "quiet term (PoseQuality.quiet_term); once, at start-up"},
    {"report", (PyCFunction)(void (*)(void))ReportChain_report, METH_FASTCALL,
     "report(t_us, cost, nis, range_m, initialized) -> solved() with the quiet term of the bound ring "
     "(ct_report_quiet; 0.0 without one)"},
    {"send", (PyCFunction)(void (*)(void))ReportChain_send, METH_FASTCALL,
     "send(write, seq, src, node, t_us, status, quality) -> errors << 8 | the next seq: the POSE frame of the "
     "last report (ct_report_frame) numbered seq and written through write (Transmitter._write_numbered's "
     "sequence and errors)"},
    {"solved", (PyCFunction)(void (*)(void))ReportChain_solved, METH_FASTCALL,
     "solved(t_us, cost, nis, quiet, range_m, initialized) -> -1 (the solution beyond range_m: nothing written) or "
     "the quality, with the tracked pose, the quaternion, the quality's row and motion and (motion bound) the "
     "covariance written (ct_report_solved)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ReportChainType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ReportChain",
    .tp_basicsize = sizeof(ReportChainObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ReportChain(n, dof, scale, max_gap_us, row, centers, prev, H, u, g, dx, d, xd, motion, sp, sR, scov, "
              "tp, tR, S, sigma, start, end, q, wl, v, cov, rms_s=0.0, motion_coils=n): one channel's report of a solved burst "
              "(MagneticTracker._report_pose) bound to its buffers (wl, v, cov None: the solver's covariance is "
              "reported as is; motion_coils 0: graded without the motion term)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ReportChain_init,
    .tp_dealloc = (destructor)ReportChain_dealloc,
    .tp_methods = ReportChain_methods,
};

/* ------------------------------------------------------------- WarmStart */
enum { WS_T, WS_D, WS_HC, WS_TP, WS_TR, WS_WP, WS_WR, WS_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_hist h;
    double *tp, *tR, *wp, *wR;
    Py_buffer views[WS_NBUF];
    int held[WS_NBUF];
    int bound;
} WarmStartObject;

static void ws_release(WarmStartObject *self)
{
    int i;
    for (i = 0; i < WS_NBUF; ++i)
        if (self->held[i]) {
            PyBuffer_Release(&self->views[i]);
            self->held[i] = 0;
        }
}

static void WarmStart_dealloc(WarmStartObject *self)
{
    ws_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int WarmStart_init(WarmStartObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"cap", "width", "t", "d", "hc", "tp", "tR", "wp", "wR", NULL};
    static const char *names[WS_NBUF] = {"t", "d", "hc", "tp", "tR", "wp", "wR"};
    static const int writable[WS_NBUF] = {0, 0, 0, 0, 0, 1, 1};
    PyObject *o[WS_NBUF];
    Py_ssize_t len[WS_NBUF];
    Py_ssize_t cap, width;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "nnOOOOOOO", kwlist, &cap, &width, &o[0], &o[1], &o[2], &o[3], &o[4],
                                     &o[5], &o[6]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "WarmStart: already bound");
        return -1;
    }
    if (cap < 2 || width != CT_HIST_WIDTH) {
        PyErr_Format(PyExc_ValueError, "WarmStart: cap must be >= 2 and width %d (the history's rows)", CT_HIST_WIDTH);
        return -1;
    }
    len[WS_T] = cap;
    len[WS_D] = cap * width;
    len[WS_HC] = 2;
    len[WS_TP] = len[WS_WP] = 3;
    len[WS_TR] = len[WS_WR] = 9;
    memset(self->held, 0, sizeof self->held);
    for (i = 0; i < WS_NBUF; ++i) {
        int ints = i == WS_T || i == WS_HC;
        if (ct_py_buffer(o[i], len[i], 8, ints ? "ql" : "d", writable[i], &self->views[i], names[i]) < 0) {
            ws_release(self);
            return -1;
        }
        self->held[i] = 1;
        if (self->views[i].len != len[i] * 8) {
            PyErr_Format(PyExc_TypeError, "%s: needs %zd items", names[i], len[i]);
            ws_release(self);
            return -1;
        }
    }
    self->h.t = self->views[WS_T].buf;
    self->h.d = self->views[WS_D].buf;
    self->h.hc = self->views[WS_HC].buf;
    self->h.cap = cap;
    self->tp = self->views[WS_TP].buf;
    self->tR = self->views[WS_TR].buf;
    self->wp = self->views[WS_WP].buf;
    self->wR = self->views[WS_WR].buf;
    self->bound = 1;
    return 0;
}

/* warm(t_ref, have_pose, initialized, range_m) -> True or False (ct_report_warm_start) */
static PyObject *WarmStart_warm(WarmStartObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t_ref;
    double range_m;
    int have, init;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "WarmStart: not bound");
        return NULL;
    }
    if (ct_py_nargs("WarmStart.warm", nargs, 4) < 0 || ct_py_int64(args[0], &t_ref) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    init = PyObject_IsTrue(args[2]);
    if (have < 0 || init < 0 || ct_py_double(args[3], &range_m) < 0)
        return NULL;
    if (ct_report_warm_start(&self->h, t_ref, have, init, range_m, self->tp, self->tR, self->wp, self->wR))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* warm_ac(t_ref, have_pose, initialized) -> True or False (ct_report_warm_start_ac: no range check) */
static PyObject *WarmStart_warm_ac(WarmStartObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t_ref;
    int have, init;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "WarmStart: not bound");
        return NULL;
    }
    if (ct_py_nargs("WarmStart.warm_ac", nargs, 3) < 0 || ct_py_int64(args[0], &t_ref) < 0)
        return NULL;
    have = PyObject_IsTrue(args[1]);
    init = PyObject_IsTrue(args[2]);
    if (have < 0 || init < 0)
        return NULL;
    if (ct_report_warm_start_ac(&self->h, t_ref, have, init, self->tp, self->tR, self->wp, self->wR))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef WarmStart_methods[] = {
    {"warm_ac", (PyCFunction)(void (*)(void))WarmStart_warm_ac, METH_FASTCALL,
     "warm_ac(t_ref, have_pose, initialized) -> whether a start was put into wp, wR "
     "(ACFusionTracker.warm_start, no range check: ct_report_warm_start_ac)"},
    {"warm", (PyCFunction)(void (*)(void))WarmStart_warm, METH_FASTCALL,
     "warm(t_ref, have_pose, initialized, range_m) -> whether a start was put into wp, wR "
     "(BurstFusionTracker.warm_start: ct_report_warm_start)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject WarmStartType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.WarmStart",
    .tp_basicsize = sizeof(WarmStartObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "WarmStart(cap, width, t, d, hc, tp, tR, wp, wR): one sensor's solve start from its fusion filter's "
              "live pose history (t, d, hc) or its tracked pose (tp, tR) into wp, wR",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)WarmStart_init,
    .tp_dealloc = (destructor)WarmStart_dealloc,
    .tp_methods = WarmStart_methods,
};

/* ------------------------------------------------------------- AheadSame */
#define AS_MAX 8

typedef struct {
    PyObject_HEAD
    int n;
    const double *a[AS_MAX], *b[AS_MAX];
    int64_t len[AS_MAX];
    Py_buffer va[AS_MAX], vb[AS_MAX];
    int bound;
} AheadSameObject;

static void as_release(AheadSameObject *self, int upto)
{
    int k;
    for (k = 0; k < upto; ++k) {
        PyBuffer_Release(&self->va[k]);
        PyBuffer_Release(&self->vb[k]);
    }
}

static void AheadSame_dealloc(AheadSameObject *self)
{
    if (self->bound)
        as_release(self, self->n);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* AheadSame(a, b): two sequences of as many float64 C-contiguous arrays, pair k of the same size */
static int AheadSame_init(AheadSameObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"a", "b", NULL};
    PyObject *sa, *sb, *fa = NULL, *fb = NULL;
    Py_ssize_t n, k;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OO", kwlist, &sa, &sb))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "AheadSame: already bound");
        return -1;
    }
    fa = PySequence_Fast(sa, "AheadSame: a must be a sequence");
    fb = fa == NULL ? NULL : PySequence_Fast(sb, "AheadSame: b must be a sequence");
    if (fb == NULL) {
        Py_XDECREF(fa);
        return -1;
    }
    n = PySequence_Fast_GET_SIZE(fa);
    if (n != PySequence_Fast_GET_SIZE(fb) || n < 1 || n > AS_MAX) {
        PyErr_Format(PyExc_ValueError, "AheadSame: a and b need the same number of arrays, 1..%d", AS_MAX);
        goto fail;
    }
    for (k = 0; k < n; ++k) {
        if (ct_py_buffer(PySequence_Fast_GET_ITEM(fa, k), 1, 8, "d", 0, &self->va[k], "a") < 0)
            goto fail_k;
        if (ct_py_buffer(PySequence_Fast_GET_ITEM(fb, k), 1, 8, "d", 0, &self->vb[k], "b") < 0) {
            PyBuffer_Release(&self->va[k]);
            goto fail_k;
        }
        if (self->va[k].len != self->vb[k].len) {
            PyBuffer_Release(&self->va[k]);
            PyBuffer_Release(&self->vb[k]);
            PyErr_SetString(PyExc_ValueError, "AheadSame: a pair of arrays of different sizes");
            goto fail_k;
        }
        self->a[k] = self->va[k].buf;
        self->b[k] = self->vb[k].buf;
        self->len[k] = self->va[k].len / 8;
    }
    self->n = (int)n;
    self->bound = 1;
    Py_DECREF(fa);
    Py_DECREF(fb);
    return 0;
fail_k:
    as_release(self, (int)k);
fail:
    Py_DECREF(fa);
    Py_DECREF(fb);
    return -1;
}

static PyObject *AheadSame_same(AheadSameObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "AheadSame: not bound");
        return NULL;
    }
    if (ct_py_nargs("AheadSame.same", nargs, 0) < 0)
        return NULL;
    if (ct_report_same(self->n, self->a, self->b, self->len))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef AheadSame_methods[] = {
    {"same", (PyCFunction)(void (*)(void))AheadSame_same, METH_FASTCALL,
     "same() -> whether every pair of the bound arrays is equal element by element (_Ahead.same: ct_report_same)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject AheadSameType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.AheadSame",
    .tp_basicsize = sizeof(AheadSameObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "AheadSame(a, b): pairs of float64 arrays compared element by element (a burst solved ahead's inputs "
              "against the burst's own)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)AheadSame_init,
    .tp_dealloc = (destructor)AheadSame_dealloc,
    .tp_methods = AheadSame_methods,
};

int ct_register_report(PyObject *m)
{
    if (PyType_Ready(&ReportChainType) < 0 || PyType_Ready(&WarmStartType) < 0 || PyType_Ready(&AheadSameType) < 0)
        return -1;
    Py_INCREF(&AheadSameType);
    if (PyModule_AddObject(m, "AheadSame", (PyObject *)&AheadSameType) < 0) {
        Py_DECREF(&AheadSameType);
        return -1;
    }
    Py_INCREF(&WarmStartType);
    if (PyModule_AddObject(m, "WarmStart", (PyObject *)&WarmStartType) < 0) {
        Py_DECREF(&WarmStartType);
        return -1;
    }
    Py_INCREF(&ReportChainType);
    if (PyModule_AddObject(m, "ReportChain", (PyObject *)&ReportChainType) < 0) {
        Py_DECREF(&ReportChainType);
        return -1;
    }
    return 0;
}
