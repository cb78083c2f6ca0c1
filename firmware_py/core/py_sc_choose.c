/*
 * CPython glue of the coil choice (src/sc_choose.c): the type ChooserCore binds a CoilChooser's
 * arrays once (start-up: its currents, bounds, weights, the products A and M, |h|^2, the
 * reductions, reference currents, posterior variances and the choice's state); choose and
 * choose_length are METH_FASTCALL, read the decision's covariance, model and limits in place and
 * return the coil as an int (a small one: no Python object created).  posterior_pose_variances is
 * the kernel of the same name on caller arrays (for the tests).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* the most pulse lengths choose_length takes */
#define CH_MAXLEN 64

enum { CH_CUR, CH_SMAX, CH_SMIN, CH_W, CH_A, CH_M, CH_HN2, CH_RED, CH_IREF, CH_VAR, CH_VAFTER, CH_ST, CH_GVAR, CH_NVIEWS };
static const char *ch_names[CH_NVIEWS] = {"currents", "sigma_max", "sigma_min", "weight", "A", "M", "hn2", "reduction", "i_ref",
                                          "var", "var_after", "st", "gain_var"};

typedef struct {
    PyObject_HEAD
    struct ct_chooser ch;
    Py_buffer views[CH_NVIEWS];
    int nviews;
} ChooserObject;

static void Chooser_release(ChooserObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void Chooser_dealloc(ChooserObject *self)
{
    Chooser_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* the items each bound array needs, for n coils and ncur currents */
static Py_ssize_t ch_len(int i, int n, int ncur)
{
    switch (i) {
    case CH_CUR: return ncur;
    case CH_SMAX: case CH_SMIN: case CH_W: case CH_VAR: case CH_VAFTER: return 6;
    case CH_A: return 18 * (Py_ssize_t)n;
    case CH_M: return 9 * (Py_ssize_t)n;
    case CH_ST: return CT_CH_NST;
    default: return n;
    }
}

/* ChooserCore(n, arrays, rel_model, current_sigma, step_a, unreached_share, trace): arrays the
 * tuple (currents, sigma_max, sigma_min, weight, A, M, hn2, reduction, i_ref, var, var_after, st, gain_var) */
static int Chooser_init(ChooserObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "arrays", "rel_model", "current_sigma", "step_a", "unreached_share", "trace", NULL};
    PyObject *arrays;
    double *ptr[CH_NVIEWS];
    int n, trace, i, ncur;
    double rel, cs, step, share;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iO!ddddp", kwlist, &n, &PyTuple_Type, &arrays, &rel, &cs, &step,
                                     &share, &trace))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "ChooserCore: already bound");
        return -1;
    }
    if (n < 1 || n > 64 || PyTuple_GET_SIZE(arrays) != CH_NVIEWS) {
        PyErr_SetString(PyExc_ValueError, "ChooserCore: n in 1..64 and 13 arrays");
        return -1;
    }
    ncur = 0;
    for (i = 0; i < CH_NVIEWS; ++i) {
        Py_ssize_t want = ch_len(i, n, ncur);
        if (ct_py_buffer(PyTuple_GET_ITEM(arrays, i), want, 8, "d", i != CH_CUR, &self->views[i], ch_names[i]) < 0) {
            Chooser_release(self);
            return -1;
        }
        self->nviews = i + 1;
        ptr[i] = (double *)self->views[i].buf;
        if (i == CH_CUR) {
            Py_ssize_t m = self->views[i].len / 8;
            if (m < 1 || m > 1000000) {
                Chooser_release(self);
                PyErr_SetString(PyExc_ValueError, "ChooserCore: 1..1000000 currents");
                return -1;
            }
            ncur = (int)m;
        }
    }
    self->ch.n = n;
    self->ch.ncur = ncur;
    self->ch.trace = trace;
    self->ch.currents = ptr[CH_CUR];
    self->ch.sigma_max = ptr[CH_SMAX];
    self->ch.sigma_min = ptr[CH_SMIN];
    self->ch.weight = ptr[CH_W];
    self->ch.A = ptr[CH_A];
    self->ch.M = ptr[CH_M];
    self->ch.hn2 = ptr[CH_HN2];
    self->ch.reduction = ptr[CH_RED];
    self->ch.i_ref = ptr[CH_IREF];
    self->ch.var = ptr[CH_VAR];
    self->ch.var_after = ptr[CH_VAFTER];
    self->ch.st = ptr[CH_ST];
    self->ch.gain_var = ptr[CH_GVAR];
    self->ch.rel_model = rel;
    self->ch.current_sigma = cs;
    self->ch.step_a = step;
    self->ch.unreached_share = share;
    return 0;
}

/* a 6 x 6 float64 matrix of any strides (the reference reads it through a memoryview) into out */
static int ch_p6(PyObject *obj, double *out)
{
    Py_buffer v;
    int i, j;
    if (!ct_py_view(obj, &v, 6, 6)) {
        PyErr_SetString(PyExc_TypeError, "P6: needs a (6, 6) float64 array");
        return -1;
    }
    for (i = 0; i < 6; ++i)
        for (j = 0; j < 6; ++j)
            out[6 * i + j] = *(const double *)((const char *)v.buf + i * v.strides[0] + j * v.strides[1]);
    PyBuffer_Release(&v);
    return 0;
}

/* the decision's model (h: n x 3, H: n x 3 x 6) and limits (n), held as read-only views */
static int ch_inputs(ChooserObject *self, PyObject *const *args, Py_buffer *v)
{
    int n = self->ch.n;
    if (ct_py_buffer(args[0], 3 * (Py_ssize_t)n, 8, "d", 0, &v[0], "h") < 0)
        return -1;
    if (ct_py_buffer(args[1], 18 * (Py_ssize_t)n, 8, "d", 0, &v[1], "H") < 0) {
        PyBuffer_Release(&v[0]);
        return -1;
    }
    if (ct_py_buffer(args[2], n, 8, "d", 0, &v[2], "i_limit") < 0) {
        PyBuffer_Release(&v[0]);
        PyBuffer_Release(&v[1]);
        return -1;
    }
    return 0;
}

static void ch_release3(Py_buffer *v)
{
    PyBuffer_Release(&v[0]);
    PyBuffer_Release(&v[1]);
    PyBuffer_Release(&v[2]);
}

static int ch_ready(ChooserObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "ChooserCore: not bound");
        return -1;
    }
    return ct_py_nargs(name, nargs, want);
}

/* 6 float64 items of a 1-D buffer of any strides into out */
static int ch_six(PyObject *obj, double *out, const char *what)
{
    Py_buffer v;
    int k;
    if (!ct_py_view(obj, &v, 6, 0)) {
        PyErr_Format(PyExc_TypeError, "%s: needs 6 float64 items", what);
        return -1;
    }
    for (k = 0; k < 6; ++k)
        out[k] = *(const double *)((const char *)v.buf + k * v.strides[0]);
    PyBuffer_Release(&v);
    return 0;
}

/* set_bounds(sigma_max6, sigma_min6) (CoilChooser.set_bounds) */
static PyObject *Chooser_set_bounds(ChooserObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double mx[6], mn[6];
    if (ch_ready(self, "set_bounds", nargs, 2) < 0 || ch_six(args[0], mx, "sigma_max6") < 0 ||
        ch_six(args[1], mn, "sigma_min6") < 0)
        return NULL;
    ct_set_bounds(&self->ch, mx, mn);
    Py_RETURN_NONE;
}

/* choose(P6, h, H, i_limit, var_amp) -> coil (CoilChooser.choose) */
static PyObject *Chooser_choose(ChooserObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double P6[36], var;
    Py_buffer v[3];
    int c;
    if (ch_ready(self, "choose", nargs, 5) < 0 || ch_p6(args[0], P6) < 0 || ct_py_double(args[4], &var) < 0 ||
        ch_inputs(self, args + 1, v) < 0)
        return NULL;
    c = ct_choose(&self->ch, P6, (const double *)v[0].buf, (const double *)v[1].buf, var, (const double *)v[2].buf);
    ch_release3(v);
    return PyLong_FromLong(c);
}

/* a sequence of 1..CH_MAXLEN numbers into out: its length, or -1 */
static int ch_numbers(PyObject *obj, double *out, const char *what)
{
    PyObject *seq = PySequence_Fast(obj, what);
    Py_ssize_t m, k;
    if (seq == NULL)
        return -1;
    m = PySequence_Fast_GET_SIZE(seq);
    if (m < 1 || m > CH_MAXLEN) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "%s: 1..%d values", what, CH_MAXLEN);
        return -1;
    }
    for (k = 0; k < m; ++k)
        if (ct_py_double(PySequence_Fast_GET_ITEM(seq, k), &out[k]) < 0) {
            Py_DECREF(seq);
            return -1;
        }
    Py_DECREF(seq);
    return (int)m;
}

/* choose_length(P6, h, H, i_limit, var_amps, lengths_us) -> coil (CoilChooser.choose_length) */
static PyObject *Chooser_choose_length(ChooserObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double P6[36], var[CH_MAXLEN], len[CH_MAXLEN];
    Py_buffer v[3];
    int c, nv, nl;
    if (ch_ready(self, "choose_length", nargs, 6) < 0 || ch_p6(args[0], P6) < 0 ||
        (nv = ch_numbers(args[4], var, "var_amps")) < 0 || (nl = ch_numbers(args[5], len, "lengths_us")) < 0)
        return NULL;
    if (nv < nl) {
        PyErr_SetString(PyExc_ValueError, "choose_length: a variance for every length");
        return NULL;
    }
    if (ch_inputs(self, args + 1, v) < 0)
        return NULL;
    c = ct_choose_length(&self->ch, P6, (const double *)v[0].buf, (const double *)v[1].buf, var, len, nl,
                         (const double *)v[2].buf);
    ch_release3(v);
    return PyLong_FromLong(c);
}

static PyMethodDef Chooser_methods[] = {
    {"set_bounds", (PyCFunction)(void (*)(void))Chooser_set_bounds, METH_FASTCALL,
     "set_bounds(sigma_max6, sigma_min6): CoilChooser.set_bounds"},
    {"choose", (PyCFunction)(void (*)(void))Chooser_choose, METH_FASTCALL,
     "choose(P6, h, H, i_limit, var_amp) -> coil: CoilChooser.choose"},
    {"choose_length", (PyCFunction)(void (*)(void))Chooser_choose_length, METH_FASTCALL,
     "choose_length(P6, h, H, i_limit, var_amps, lengths_us) -> coil: CoilChooser.choose_length"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ChooserType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ChooserCore",
    .tp_basicsize = sizeof(ChooserObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ChooserCore(n, arrays, rel_model, current_sigma, step_a, unreached_share, trace): the adaptive "
              "single-coil policy's coil choice bound to a CoilChooser's arrays (actuate.coil_choice)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Chooser_init,
    .tp_dealloc = (destructor)Chooser_dealloc,
    .tp_methods = Chooser_methods,
};

/* posterior_pose_variances(P6, A, M, hnorm2, current, var_amp, rel_model, out, current_sigma) -> bool */
static PyObject *py_posterior(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double P6[36], hn2, cur, var, rel, cs;
    Py_buffer a, m, o;
    int ok;
    (void)mod;
    if (ct_py_nargs("posterior_pose_variances", nargs, 9) < 0 || ch_p6(args[0], P6) < 0 ||
        ct_py_double(args[3], &hn2) < 0 || ct_py_double(args[4], &cur) < 0 || ct_py_double(args[5], &var) < 0 ||
        ct_py_double(args[6], &rel) < 0 || ct_py_double(args[8], &cs) < 0)
        return NULL;
    if (ct_py_buffer(args[1], 18, 8, "d", 0, &a, "A") < 0)
        return NULL;
    if (ct_py_buffer(args[2], 9, 8, "d", 0, &m, "M") < 0) {
        PyBuffer_Release(&a);
        return NULL;
    }
    if (ct_py_buffer(args[7], 6, 8, "d", 1, &o, "out") < 0) {
        PyBuffer_Release(&a);
        PyBuffer_Release(&m);
        return NULL;
    }
    ok = ct_posterior_pose_variances(P6, (const double *)a.buf, (const double *)m.buf, hn2, cur, var, rel,
                                     (double *)o.buf, cs);
    PyBuffer_Release(&a);
    PyBuffer_Release(&m);
    PyBuffer_Release(&o);
    return PyBool_FromLong(ok);
}

static PyMethodDef ch_functions[] = {
    {"posterior_pose_variances", (PyCFunction)(void (*)(void))py_posterior, METH_FASTCALL,
     "posterior_pose_variances(P6, A, M, hnorm2, current, var_amp, rel_model, out, current_sigma) -> bool: "
     "coil_choice.posterior_pose_variances"},
    {NULL, NULL, 0, NULL}};

int ct_register_sc_choose(PyObject *m)
{
    if (PyType_Ready(&ChooserType) < 0)
        return -1;
    Py_INCREF(&ChooserType);
    if (PyModule_AddObject(m, "ChooserCore", (PyObject *)&ChooserType) < 0) {
        Py_DECREF(&ChooserType);
        return -1;
    }
    if (PyModule_AddFunctions(m, ch_functions) < 0 || PyModule_AddIntConstant(m, "CH_NST", CT_CH_NST) < 0 ||
        PyModule_AddIntConstant(m, "CH_MAXLEN", CH_MAXLEN) < 0)
        return -1;
    return 0;
}
