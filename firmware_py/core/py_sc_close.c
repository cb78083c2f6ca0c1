/*
 * CPython glue of the single-coil window close (track.single_coil_tracker.SingleCoilTracker._close_one):
 * - SuspectSpan (src/sc_close.c) binds the supervisor's state arrays (si int64, sd float64:
 *   ct_supervise.h's layout, the arrays Health.use_arrays keeps its lists in) once at construction;
 *   either(node, other, t0, t1) returns a bool;
 * - ScWindowUpdate binds one sensor's window update once: its ScUpdateCore and the tracker's
 *   SharedBaselinesCore (py_sc_window.c), its filter's SchepersCore and SingleCoilUpdateCore
 *   (py_single_coil.c), its covariance, the channel's amplitude and the counters the reference keeps
 *   (py_sc_close.h); run(k, coil, current) is SingleCoilTracker._update's window_prior, channel_variance,
 *   SchepersEKF.update_pulse (with SingleCoilUpdate._run_fused's bookkeeping) and window_after in one
 *   call, the same kernels in the same order.
 * - symmetrize(P, T) (src/fusimu.c ct_symmetrize: T a copy of P, P[i][j] = (T[i][j] + T[j][i]) * 0.5, numpy's
 *   np.add(T, T.T, out=P), np.multiply(P, 0.5, out=P)): estimate.ekf.symmetrize.
 * All METH_FASTCALL; they read their arguments in place (no Python object created but the result).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_sc_close.h"

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

/* ------------------------------------------------------------- ScWindowUpdate */
enum { WU_P, WU_AMP, WU_KST, WU_KNIS, WU_UST, WU_UCNT, WU_OUT, WU_N };
/* out[]: the update's consistency term, whether its NIS tested the linear model, the model's evaluations */
enum { WU_X, WU_LINEAR, WU_EVALS, WU_NOUT };

typedef struct {
    PyObject_HEAD
    PyObject *uc, *sb, *scu, *sc;          /* held */
    struct ct_sc *s;                       /* sc's state */
    int64_t ch, n_clones, pos0, ori0, ncoils;
    double gate;
    long iters;
    double *P, *knis, *ust, *out;
    const double *amp;
    int64_t *kst, *ucnt;
    Py_buffer views[WU_N];
    int nviews;
} WuObject;

static void Wu_release(WuObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    Py_CLEAR(self->uc);
    Py_CLEAR(self->sb);
    Py_CLEAR(self->scu);
    Py_CLEAR(self->sc);
}

static void Wu_dealloc(WuObject *self)
{
    Wu_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* ScWindowUpdate(uc, sb, channel, scu, sc, P, amp, pos, ori, gate, iterations, kst, knis, ust, ucnt, out) */
static int Wu_init(WuObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"uc", "sb", "channel", "scu", "sc", "P", "amp", "pos", "ori", "gate", "iterations",
                             "kst", "knis", "ust", "ucnt", "out", NULL};
    PyObject *uc, *sb, *scu, *sc, *o[WU_N];
    long long ch, pos, ori;
    long iters;
    double gate;
    struct ct_sc *s;
    static const char *names[WU_N] = {"P", "amp", "kst", "knis", "ust", "ucnt", "out"};
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOLOOOOLLdlOOOOO", kwlist, &uc, &sb, &ch, &scu, &sc, &o[WU_P],
                                     &o[WU_AMP], &pos, &ori, &gate, &iters, &o[WU_KST], &o[WU_KNIS], &o[WU_UST],
                                     &o[WU_UCNT], &o[WU_OUT]))
        return -1;
    if (self->nviews || self->uc) {
        PyErr_SetString(PyExc_RuntimeError, "ScWindowUpdate: already bound");
        return -1;
    }
    s = ct_py_sc_state(sc);
    if (!ct_py_scw_ready(uc) || s == NULL || !ct_py_scu_ready(scu, s->nx) || ch < 0 ||
        ch >= ct_py_sb_channels(sb)) {
        PyErr_SetString(PyExc_TypeError, "ScWindowUpdate: a bound ScUpdateCore, SharedBaselinesCore with the "
                                         "channel bound, SingleCoilUpdateCore with its run bound, SchepersCore");
        return -1;
    }
    if (iters < 1 || pos < 0 || pos + 3 > s->nx || ori < 0 || ori + 3 > s->nx) {
        PyErr_SetString(PyExc_ValueError, "ScWindowUpdate: iterations >= 1, pos and ori rows inside the state");
        return -1;
    }
    for (i = 0; i < WU_N; ++i) {
        Py_ssize_t n;
        const char *fmt = "d";
        switch (i) {
        case WU_P: n = (Py_ssize_t)s->nx * s->nx; break;
        case WU_AMP: n = 3; break;
        case WU_KST: case WU_UCNT: n = 2; fmt = "ql"; break;
        case WU_KNIS: n = 1; break;
        case WU_UST: n = 2; break;
        default: n = WU_NOUT;
        }
        if (ct_py_buffer(o[i], n, 8, fmt, i != WU_AMP, &self->views[i], names[i]) < 0) {
            Wu_release(self);
            return -1;
        }
        self->nviews = i + 1;
    }
    if ((double *)self->views[WU_P].buf != s->P) {
        Wu_release(self);
        PyErr_SetString(PyExc_ValueError, "ScWindowUpdate: P must be the filter's covariance SchepersCore holds");
        return -1;
    }
    self->P = (double *)self->views[WU_P].buf;
    self->amp = (const double *)self->views[WU_AMP].buf;
    self->kst = (int64_t *)self->views[WU_KST].buf;
    self->knis = (double *)self->views[WU_KNIS].buf;
    self->ust = (double *)self->views[WU_UST].buf;
    self->ucnt = (int64_t *)self->views[WU_UCNT].buf;
    self->out = (double *)self->views[WU_OUT].buf;
    Py_INCREF(uc);
    Py_INCREF(sb);
    Py_INCREF(scu);
    Py_INCREF(sc);
    self->uc = uc;
    self->sb = sb;
    self->scu = scu;
    self->sc = sc;
    self->s = s;
    self->ch = ch;
    self->n_clones = ct_py_scw_clones(uc) < s->nc ? ct_py_scw_clones(uc) : s->nc;
    self->pos0 = pos;
    self->ori0 = ori;
    self->ncoils = ct_py_scu_coils(scu);
    self->gate = gate;
    self->iters = iters;
    return 0;
}

/* run(k, coil, current) -> flags: the window update of clone k (-1: the state) with coil's amplitude
 * (the bound channel's) at current; -1 (nothing done) when clone k is not taken yet */
static PyObject *Wu_run(WuObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k, coil;
    double current, rel, gate, x;
    const double *p, *R, *var, *mst;
    long cp, co;
    struct ct_sc *s = self->s;
    struct ct_py_scu_out r;
    int flags, linear;
    if (self->uc == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ScWindowUpdate: not bound");
        return NULL;
    }
    if (ct_py_nargs("run", nargs, 3) < 0 || ct_py_int64(args[0], &k) < 0 || ct_py_int64(args[1], &coil) < 0 ||
        ct_py_double(args[2], &current) < 0)
        return NULL;
    if (k < -1 || k >= self->n_clones || coil < 0 || coil >= self->ncoils) {
        PyErr_SetString(PyExc_IndexError, "ScWindowUpdate.run: no such clone or coil");
        return NULL;
    }
    /* SchepersEKF.update_pulse: a clone the IMU stream has not reached is the reference's to take */
    if (k >= 0 && !s->cl_taken[k])
        return PyLong_FromLong(-1);
    rel = ct_py_scw_prior(self->uc, k, current);                        /* window_prior */
    var = ct_py_sb_variance(self->sb, self->ch);                          /* channel_variance */
    mst = ct_py_scw_monitor_state(self->uc);                              /* mon.r_scale, not mon.inconsistent */
    gate = mst[CT_NIS_INCONSISTENT] != 0.0 ? HUGE_VAL : self->gate;
    if (k >= 0) {
        p = s->cl_p + 3 * k;
        R = s->cl_R + 9 * k;
        cp = s->cp[k];
        co = s->co[k];
    } else {
        p = s->p;
        R = s->R;
        cp = (long)self->pos0;
        co = (long)self->ori0;
    }
    flags = ct_py_scu_run(self->scu, self->P, p, R, cp, co, (long)coil, self->amp, var, current, rel,
                          mst[CT_NIS_R_SCALE], gate, self->iters, (long long)self->kst[0], &r);
    self->kst[0] += r.applied;                                            /* KalmanUpdate.add_counts */
    self->kst[1] += r.rejected;
    self->knis[0] = r.nis_last;
    self->ust[0] = r.nis_nominal;                                         /* SchepersEKF.nis_nominal, nis */
    self->ust[1] = r.nis;
    self->out[WU_EVALS] = r.evals;
    if (flags & (CT_EKF_GATED | CT_EKF_NOT_PD | CT_EKF_NONFINITE)) {
        self->ucnt[0] += 1;                                               /* rejected */
    } else {
        ct_sc_inject(s, r.dx);                                            /* SchepersEKF._inject */
        self->ucnt[1] += 1;                                               /* updates */
    }
    if (!(flags & (CT_EKF_NOT_PD | CT_EKF_NONFINITE))) {
        x = ct_py_scw_after(self->uc, self->ust[0], self->ust[1], &linear);   /* window_after */
        self->out[WU_X] = x;
        self->out[WU_LINEAR] = linear ? 1.0 : 0.0;
    }
    return PyLong_FromLong(flags);
}

static PyMethodDef Wu_methods[] = {
    {"run", (PyCFunction)(void (*)(void))Wu_run, METH_FASTCALL,
     "run(k, coil, current) -> flags: SingleCoilTracker._update's prior, variance, update and after-steps in one "
     "call (out: the consistency term, the linear flag, the evaluations); -1 when clone k is not taken"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject WuType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ScWindowUpdate",
    .tp_basicsize = sizeof(WuObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ScWindowUpdate(uc, sb, channel, scu, sc, P, amp, pos, ori, gate, iterations, kst, knis, ust, ucnt, "
              "out): one sensor's single-coil window update in one call, bound once",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Wu_init,
    .tp_dealloc = (destructor)Wu_dealloc,
    .tp_methods = Wu_methods,
};

/* ------------------------------------------------------------- symmetrize */
/* symmetrize(P, T) -> bool: estimate.ekf.symmetrize on two C-contiguous n x n float64 arrays; False
 * (nothing done) for arrays it cannot take, which the caller then gives to the reference */
static PyObject *py_symmetrize(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv, tv;
    const int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE;
    int ok;
    (void)mod;
    if (ct_py_nargs("symmetrize", nargs, 2) < 0)
        return NULL;
    if (PyObject_GetBuffer(args[0], &pv, flags) < 0) {
        PyErr_Clear();
        Py_RETURN_FALSE;
    }
    if (PyObject_GetBuffer(args[1], &tv, flags) < 0) {
        PyErr_Clear();
        PyBuffer_Release(&pv);
        Py_RETURN_FALSE;
    }
    ok = pv.ndim == 2 && tv.ndim == 2 && pv.itemsize == 8 && tv.itemsize == 8 && pv.format != NULL &&
         tv.format != NULL && pv.format[0] == 'd' && pv.format[1] == 0 && tv.format[0] == 'd' && tv.format[1] == 0 &&
         pv.shape[0] == pv.shape[1] && tv.shape[0] == pv.shape[0] && tv.shape[1] == pv.shape[0] && pv.buf != tv.buf &&
         pv.shape[0] <= 4096;
    if (ok)
        ct_symmetrize((int)pv.shape[0], (double *)pv.buf, (double *)tv.buf);
    PyBuffer_Release(&tv);
    PyBuffer_Release(&pv);
    if (ok)
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef sc_close_functions[] = {
    {"symmetrize", (PyCFunction)(void (*)(void))py_symmetrize, METH_FASTCALL,
     "symmetrize(P, T) -> bool: estimate.ekf.symmetrize (P = (P + P^T) / 2 through T); False for arrays it cannot "
     "take (not both C-contiguous square float64 of one size, or the same memory)"},
    {NULL, NULL, 0, NULL}};

int ct_register_sc_close(PyObject *m)
{
    if (ct_py_add_type(m, &SuspectSpanType, "SuspectSpan") < 0 || ct_py_add_type(m, &WuType, "ScWindowUpdate") < 0 ||
        PyModule_AddFunctions(m, sc_close_functions) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "WU_NOUT", WU_NOUT) < 0)
        return -1;
    return 0;
}
