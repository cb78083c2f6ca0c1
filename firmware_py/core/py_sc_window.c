/*
 * CPython glue of the single-coil window close's shared baselines (src/sc_window.c): the type
 * SharedBaselinesCore binds a SharedBaselines' state (its integers and floats, two arrays) and
 * its variance buffer once at construction, and with bind_channels the sensor channels' last
 * window (amp_var (3,) float64, info (4,) int64 each); its methods are METH_FASTCALL and read
 * their integers in place; variance returns None (no Python object created); close (the shared
 * fractions), predicted and chained (a decision's variances) return their float.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_sc_close.h"

/* the most sensor channels bind_channels takes */
#define SB_MAXCH 64

typedef struct {
    PyObject_HEAD
    int64_t *si;
    double *sf, *var;
    const double *amp_var[SB_MAXCH];
    const int64_t *info[SB_MAXCH];
    Py_buffer views[3 + 2 * SB_MAXCH];
    int nviews, nch;
} SbObject;

static void Sb_release(SbObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    self->nch = 0;
}

static void Sb_dealloc(SbObject *self)
{
    Sb_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* SharedBaselinesCore(si, sf, var): si int64 (CT_SB_NI), sf float64 (CT_SB_NF), var float64 (3) */
static int Sb_init(SbObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"si", "sf", "var", NULL};
    PyObject *si, *sf, *var;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOO", kwlist, &si, &sf, &var))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SharedBaselinesCore: already bound");
        return -1;
    }
    if (ct_py_buffer(si, CT_SB_NI, 8, "ql", 1, &self->views[0], "si") < 0)
        return -1;
    self->nviews = 1;
    if (ct_py_buffer(sf, CT_SB_NF, 8, "d", 1, &self->views[1], "sf") < 0) {
        Sb_release(self);
        return -1;
    }
    self->nviews = 2;
    if (ct_py_buffer(var, 3, 8, "d", 1, &self->views[2], "var") < 0) {
        Sb_release(self);
        return -1;
    }
    self->nviews = 3;
    self->si = (int64_t *)self->views[0].buf;
    self->sf = (double *)self->views[1].buf;
    self->var = (double *)self->views[2].buf;
    return 0;
}

static int Sb_ready(SbObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (self->nviews < 3) {
        PyErr_SetString(PyExc_RuntimeError, "SharedBaselinesCore: not bound");
        return -1;
    }
    return ct_py_nargs(name, nargs, want);
}

/* bind_channels(channels): a tuple (amp_var_0, info_0, amp_var_1, info_1, ...), once */
static PyObject *Sb_bind_channels(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    PyObject *t;
    Py_ssize_t m, k;
    if (Sb_ready(self, "bind_channels", nargs, 1) < 0)
        return NULL;
    t = args[0];
    if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) % 2 != 0 || PyTuple_GET_SIZE(t) / 2 > SB_MAXCH) {
        PyErr_Format(PyExc_ValueError, "bind_channels: a tuple of (amp_var, info) pairs, at most %d", SB_MAXCH);
        return NULL;
    }
    if (self->nch || self->nviews > 3) {
        PyErr_SetString(PyExc_RuntimeError, "bind_channels: already bound");
        return NULL;
    }
    m = PyTuple_GET_SIZE(t) / 2;
    for (k = 0; k < m; ++k) {
        if (ct_py_buffer(PyTuple_GET_ITEM(t, 2 * k), 3, 8, "d", 0, &self->views[self->nviews], "amp_var") < 0)
            goto fail;
        self->amp_var[k] = (const double *)self->views[self->nviews++].buf;
        if (ct_py_buffer(PyTuple_GET_ITEM(t, 2 * k + 1), 4, 8, "ql", 0, &self->views[self->nviews], "info") < 0)
            goto fail;
        self->info[k] = (const int64_t *)self->views[self->nviews++].buf;
    }
    self->nch = (int)m;
    Py_RETURN_NONE;
fail:
    while (self->nviews > 3)
        PyBuffer_Release(&self->views[--self->nviews]);
    return NULL;
}

/* close(start, end, next_start, earliest_next_us) (SharedBaselines.close; shared into sf, and returned) */
static PyObject *Sb_close(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[4];
    int k;
    if (Sb_ready(self, "close", nargs, 4) < 0)
        return NULL;
    for (k = 0; k < 4; ++k)
        if (ct_py_int64(args[k], &v[k]) < 0)
            return NULL;
    return PyFloat_FromDouble(ct_sb_close(self->si, self->sf, v[0], v[1], v[2], v[3]));
}

/* variance(k): channel k's bound amp_var and info (SharedBaselines.variance) into var */
static PyObject *Sb_variance(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    if (Sb_ready(self, "variance", nargs, 1) < 0 || ct_py_int64(args[0], &k) < 0)
        return NULL;
    if (k < 0 || k >= self->nch) {
        PyErr_SetString(PyExc_IndexError, "variance: no such bound channel");
        return NULL;
    }
    ct_sb_variance(self->si, self->sf, self->amp_var[k], self->info[k], self->var);
    Py_RETURN_NONE;
}

/* variance_of(amp_var, info): the same on caller arrays (the tests; the reference's call) */
static PyObject *Sb_variance_of(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer a, i;
    if (Sb_ready(self, "variance_of", nargs, 2) < 0)
        return NULL;
    if (ct_py_buffer(args[0], 3, 8, "d", 0, &a, "amp_var") < 0)
        return NULL;
    if (ct_py_buffer(args[1], 4, 8, "ql", 0, &i, "info") < 0) {
        PyBuffer_Release(&a);
        return NULL;
    }
    ct_sb_variance(self->si, self->sf, (const double *)a.buf, (const int64_t *)i.buf, self->var);
    PyBuffer_Release(&a);
    PyBuffer_Release(&i);
    Py_RETURN_NONE;
}

/* predicted(var_amp, start, prev_end) (SharedBaselines.predicted): a float */
static PyObject *Sb_predicted(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v;
    int64_t start, prev;
    if (Sb_ready(self, "predicted", nargs, 3) < 0 || ct_py_double(args[0], &v) < 0 || ct_py_int64(args[1], &start) < 0
        || ct_py_int64(args[2], &prev) < 0)
        return NULL;
    return PyFloat_FromDouble(ct_sb_predicted(self->si, self->sf, v, start, prev));
}

/* chained(var_amp) (SharedBaselines.chained): a float */
static PyObject *Sb_chained(SbObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v;
    if (Sb_ready(self, "chained", nargs, 1) < 0 || ct_py_double(args[0], &v) < 0)
        return NULL;
    return PyFloat_FromDouble(ct_sb_chained(self->si, self->sf, v));
}

static PyMethodDef Sb_methods[] = {
    {"bind_channels", (PyCFunction)(void (*)(void))Sb_bind_channels, METH_FASTCALL,
     "bind_channels((amp_var_0, info_0, ...)): the channels' last windows, bound once"},
    {"close", (PyCFunction)(void (*)(void))Sb_close, METH_FASTCALL,
     "close(start, end, next_start, earliest_next_us) -> shared: SharedBaselines.close"},
    {"variance", (PyCFunction)(void (*)(void))Sb_variance, METH_FASTCALL,
     "variance(k): SharedBaselines.variance of bound channel k into var"},
    {"variance_of", (PyCFunction)(void (*)(void))Sb_variance_of, METH_FASTCALL,
     "variance_of(amp_var, info): SharedBaselines.variance into var"},
    {"predicted", (PyCFunction)(void (*)(void))Sb_predicted, METH_FASTCALL,
     "predicted(var_amp, start, prev_end): SharedBaselines.predicted"},
    {"chained", (PyCFunction)(void (*)(void))Sb_chained, METH_FASTCALL,
     "chained(var_amp): SharedBaselines.chained"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SbType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SharedBaselinesCore",
    .tp_basicsize = sizeof(SbObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SharedBaselinesCore(si, sf, var): estimate.shared_baseline.SharedBaselines' close and variance "
              "bound to its state arrays",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Sb_init,
    .tp_dealloc = (destructor)Sb_dealloc,
    .tp_methods = Sb_methods,
};

/* ---------------------------------------------------------------- ScUpdateCore */
/* one sensor's window update around the one-call update (SingleCoilTracker._update's window_prior
 * and window_after): its filter's covariance, position and clones' positions, its NIS monitor's
 * arrays and constants (track.single_coil_nis.CompiledNisMonitor), its magnetometer ring (bind_quiet),
 * the linearisation flag w[0] (1.0: the last prior's NIS tests the linear model) */
enum { SU_P, SU_POS, SU_CLONES, SU_BUF, SU_BOUND, SU_ST, SU_W, SU_HC, SU_B, SU_N };

typedef struct {
    PyObject_HEAD
    struct ct_nis mon;
    const double *P, *p, *clone_p, *qb;
    const int64_t *qhc;
    double *w;
    int64_t nP, pos, n_clones, qcap;
    double lin2, rel2, tol_a, earth, quiet_sigma;
    int quiet, linear;
    Py_buffer views[SU_N];
    int held[SU_N];
} SuObject;

static void Su_release(SuObject *self)
{
    int i;
    for (i = 0; i < SU_N; ++i)
        if (self->held[i]) {
            PyBuffer_Release(&self->views[i]);
            self->held[i] = 0;
        }
    self->quiet = 0;
}

static void Su_dealloc(SuObject *self)
{
    Su_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Su_bind(SuObject *self, int i, PyObject *o, Py_ssize_t n, const char *formats, int writable,
                   const char *what)
{
    if (ct_py_buffer(o, n, 8, formats, writable, &self->views[i], what) < 0)
        return -1;
    self->held[i] = 1;
    return 0;
}

/* ScUpdateCore(P, nP, pos, p, clone_p, buf, bound, st, window, min_count, dof, min_mean, max_scale,
 * excess_gate, alpha, lin2, rel2, tol_a, w) */
static int Su_init(SuObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"P", "nP", "pos", "p", "clone_p", "buf", "bound", "st", "window", "min_count", "dof",
                             "min_mean", "max_scale", "excess_gate", "alpha", "lin2", "rel2", "tol_a", "w", NULL};
    PyObject *P, *p, *cp, *buf, *bound, *st, *w;
    long long nP, pos;
    struct ct_nis *m = &self->mon;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OLLOOOOOiiddddddddO", kwlist, &P, &nP, &pos, &p, &cp, &buf, &bound,
                                     &st, &m->window, &m->min_count, &m->dof, &m->min_mean, &m->max_scale,
                                     &m->excess_gate, &m->alpha, &self->lin2, &self->rel2, &self->tol_a, &w))
        return -1;
    if (self->held[SU_P]) {
        PyErr_SetString(PyExc_RuntimeError, "ScUpdateCore: already bound");
        return -1;
    }
    if (nP < 3 || pos < 0 || pos + 3 > nP || m->window < 1 || m->min_count < 1 || m->min_count > m->window ||
        !(m->dof > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "ScUpdateCore: need 0 <= pos <= nP - 3, 1 <= min_count <= window, dof > 0");
        return -1;
    }
    if (Su_bind(self, SU_P, P, (Py_ssize_t)(nP * nP), "d", 0, "P") < 0 || Su_bind(self, SU_POS, p, 3, "d", 0, "p") < 0 ||
        Su_bind(self, SU_CLONES, cp, 0, "d", 0, "clone_p") < 0 ||
        Su_bind(self, SU_BUF, buf, m->window, "d", 1, "buf") < 0 ||
        Su_bind(self, SU_BOUND, bound, m->window + 1, "d", 0, "bound") < 0 ||
        Su_bind(self, SU_ST, st, CT_NIS_NST, "d", 1, "st") < 0 || Su_bind(self, SU_W, w, 1, "d", 1, "w") < 0) {
        Su_release(self);
        return -1;
    }
    self->nP = nP;
    self->pos = pos;
    self->P = (const double *)self->views[SU_P].buf;
    self->p = (const double *)self->views[SU_POS].buf;
    self->clone_p = (const double *)self->views[SU_CLONES].buf;
    self->n_clones = (int64_t)(self->views[SU_CLONES].len / 24);
    m->buf = (double *)self->views[SU_BUF].buf;
    m->bound = (const double *)self->views[SU_BOUND].buf;
    m->st = (double *)self->views[SU_ST].buf;
    self->w = (double *)self->views[SU_W].buf;
    return 0;
}

static int Su_ready(SuObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (!self->held[SU_P]) {
        PyErr_SetString(PyExc_RuntimeError, "ScUpdateCore: not bound");
        return -1;
    }
    return ct_py_nargs(name, nargs, want);
}

/* bind_quiet(hc, b, earth, quiet_sigma): the sensor's magnetometer ring (hc int64 (2,): head, count;
 * b float64 (cap, 3)) whose newest sample gives the consistency's quiet term; once */
static PyObject *Su_bind_quiet(SuObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (Su_ready(self, "bind_quiet", nargs, 4) < 0)
        return NULL;
    if (self->quiet) {
        PyErr_SetString(PyExc_RuntimeError, "ScUpdateCore.bind_quiet: a ring bound already");
        return NULL;
    }
    if (ct_py_double(args[2], &self->earth) < 0 || ct_py_double(args[3], &self->quiet_sigma) < 0)
        return NULL;
    if (Su_bind(self, SU_HC, args[0], 2, "ql", 0, "hc") < 0)
        return NULL;
    if (Su_bind(self, SU_B, args[1], 3, "d", 0, "b") < 0) {
        PyBuffer_Release(&self->views[SU_HC]);
        self->held[SU_HC] = 0;
        return NULL;
    }
    self->qhc = (const int64_t *)self->views[SU_HC].buf;
    self->qb = (const double *)self->views[SU_B].buf;
    self->qcap = (int64_t)(self->views[SU_B].len / 24);
    self->quiet = 1;
    Py_RETURN_NONE;
}

/* prior(k, current): rel (a float), w[0] the linearisation flag; k the clone (-1: the state) */
static PyObject *Su_prior(SuObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    double current, rel;
    const double *p;
    if (Su_ready(self, "prior", nargs, 2) < 0 || ct_py_int64(args[0], &k) < 0 || ct_py_double(args[1], &current) < 0)
        return NULL;
    if (k >= self->n_clones) {
        PyErr_SetString(PyExc_IndexError, "prior: no such clone");
        return NULL;
    }
    p = k >= 0 ? self->clone_p + 3 * k : self->p;
    rel = ct_scw_prior(self->P, self->nP, self->pos, p, self->lin2, self->rel2, self->tol_a, current, &self->linear);
    self->w[0] = self->linear ? 1.0 : 0.0;
    return PyFloat_FromDouble(rel);
}

/* after(nis_nominal, nis): the consistency x (a float); the monitor's add and add_used when the last
 * prior was linear */
static PyObject *Su_after(SuObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double nn, nis;
    if (Su_ready(self, "after", nargs, 2) < 0 || ct_py_double(args[0], &nn) < 0 || ct_py_double(args[1], &nis) < 0)
        return NULL;
    return PyFloat_FromDouble(ct_scw_after(&self->mon, self->qhc, self->qb, self->qcap, self->quiet, self->earth,
                                           self->quiet_sigma, nn, nis, self->linear));
}

static PyMethodDef Su_methods[] = {
    {"bind_quiet", (PyCFunction)(void (*)(void))Su_bind_quiet, METH_FASTCALL,
     "bind_quiet(hc, b, earth, quiet_sigma): the sensor's magnetometer ring for the quiet term, once"},
    {"prior", (PyCFunction)(void (*)(void))Su_prior, METH_FASTCALL,
     "prior(k, current) -> rel: window_prior (ct_scw_prior), the linearisation flag into w[0]"},
    {"after", (PyCFunction)(void (*)(void))Su_after, METH_FASTCALL,
     "after(nis_nominal, nis) -> x: window_after (ct_scw_after)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SuType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ScUpdateCore",
    .tp_basicsize = sizeof(SuObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ScUpdateCore(P, nP, pos, p, clone_p, buf, bound, st, window, min_count, dof, min_mean, max_scale, "
              "excess_gate, alpha, lin2, rel2, tol_a, w): one sensor's single-coil window update around its "
              "one-call update (track.single_coil_tracker window_prior, window_after)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Su_init,
    .tp_dealloc = (destructor)Su_dealloc,
    .tp_methods = Su_methods,
};

int ct_register_sc_window(PyObject *m)
{
    if (ct_py_add_type(m, &SuType, "ScUpdateCore") < 0 || ct_py_add_type(m, &SbType, "SharedBaselinesCore") < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "SB_NI", CT_SB_NI) < 0 || PyModule_AddIntConstant(m, "SB_NF", CT_SB_NF) < 0 ||
        PyModule_AddIntConstant(m, "SB_MAXCH", SB_MAXCH) < 0)
        return -1;
    return 0;
}

/* ------------------------------------------------- for py_sc_close.c (py_sc_close.h) */
int ct_py_scw_ready(PyObject *o)
{
    return PyObject_TypeCheck(o, &SuType) && ((SuObject *)o)->held[SU_P];
}

int64_t ct_py_scw_clones(PyObject *o)
{
    return ((SuObject *)o)->n_clones;
}

double ct_py_scw_prior(PyObject *o, int64_t k, double current)
{
    SuObject *self = (SuObject *)o;
    const double *p = k >= 0 ? self->clone_p + 3 * k : self->p;
    double rel = ct_scw_prior(self->P, self->nP, self->pos, p, self->lin2, self->rel2, self->tol_a, current,
                              &self->linear);
    self->w[0] = self->linear ? 1.0 : 0.0;
    return rel;
}

double ct_py_scw_after(PyObject *o, double nis_nominal, double nis, int *linear)
{
    SuObject *self = (SuObject *)o;
    *linear = self->linear;
    return ct_scw_after(&self->mon, self->qhc, self->qb, self->qcap, self->quiet, self->earth, self->quiet_sigma,
                        nis_nominal, nis, self->linear);
}

const double *ct_py_scw_monitor_state(PyObject *o)
{
    return ((SuObject *)o)->mon.st;
}

int ct_py_sb_channels(PyObject *o)
{
    return PyObject_TypeCheck(o, &SbType) && ((SbObject *)o)->nviews >= 3 ? ((SbObject *)o)->nch : -1;
}

const double *ct_py_sb_variance(PyObject *o, int64_t k)
{
    SbObject *self = (SbObject *)o;
    ct_sb_variance(self->si, self->sf, self->amp_var[k], self->info[k], self->var);
    return self->var;
}
