/*
 * CPython glue of the single-coil EKF kernels (src/single_coil.c, include/ct_single_coil.h):
 * SchepersCore binds one coiltrack.firmware.estimate.single_coil.SchepersEKF's arrays and
 * SingleCoilUpdateCore one estimate.single_coil_update.SingleCoilUpdate's, once, at construction;
 * the per-call methods are METH_FASTCALL, read their arguments in place (small vectors that may be
 * strided views are copied into locals) and create no Python object (None, a small int or a bool).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_sc_close.h"

/* ------------------------------------------------------------------ buffers */
static int sc_is_format(const Py_buffer *v, char want, Py_ssize_t itemsize)
{
    const char *f = v->format;
    if (v->itemsize != itemsize || f == NULL)
        return 0;
    if (f[0] == '@' || f[0] == '=' || f[0] == '<')
        f++;
    if (want == 'q')                 /* a 64-bit signed integer: 'q' or 'l' where long is 64-bit */
        return (f[0] == 'q' || (f[0] == 'l' && sizeof(long) == 8)) && f[1] == '\0';
    return f[0] == want && f[1] == '\0';
}

/* a C-contiguous buffer of at least n items of format `fmt` ('d', 'q', '?'), or -1 with TypeError */
static int sc_get(PyObject *obj, Py_ssize_t n, char fmt, Py_ssize_t itemsize, int writable, Py_buffer *view,
                  const char *what)
{
    const char one[2] = {fmt, '\0'};
    return ct_py_buffer(obj, n, itemsize, fmt == 'q' ? "ql" : one, writable, view, what);
}

static int sc_doubles(PyObject *obj, Py_ssize_t n, int writable, Py_buffer *view, const char *what)
{
    return sc_get(obj, n, 'd', (Py_ssize_t)sizeof(double), writable, view, what);
}

/* n float64 items of a buffer of any strides (a view such as a column of a matrix) into out */
static int sc_copy_doubles(PyObject *obj, int n, double *out, const char *what)
{
    Py_buffer v;
    Py_ssize_t total = 1, idx[3] = {0, 0, 0};
    int i, d;
    if (PyObject_GetBuffer(obj, &v, PyBUF_RECORDS_RO) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: needs a float64 buffer", what);
        return -1;
    }
    for (d = 0; d < v.ndim; ++d)
        total *= v.shape[d];
    if (!sc_is_format(&v, 'd', (Py_ssize_t)sizeof(double)) || v.ndim < 1 || v.ndim > 3 || total != n) {
        PyBuffer_Release(&v);
        PyErr_Format(PyExc_TypeError, "%s: needs %d float64 items", what, n);
        return -1;
    }
    for (i = 0; i < n; ++i) {
        const char *ptr = (const char *)v.buf;
        for (d = 0; d < v.ndim; ++d)
            ptr += idx[d] * v.strides[d];
        memcpy(&out[i], ptr, sizeof(double));
        for (d = v.ndim - 1; d >= 0; --d) {       /* row-major odometer */
            if (++idx[d] < v.shape[d])
                break;
            idx[d] = 0;
        }
    }
    PyBuffer_Release(&v);
    return 0;
}

static int sc_double(PyObject *o, double *x)
{
    return ct_py_double(o, x);
}

static int sc_int(PyObject *o, long lo, long hi, long *x, const char *what)
{
    *x = PyLong_AsLong(o);
    if (*x == -1 && PyErr_Occurred())
        return -1;
    if (*x < lo || *x > hi) {
        PyErr_Format(PyExc_ValueError, "%s must be in %ld..%ld, got %ld", what, lo, hi, *x);
        return -1;
    }
    return 0;
}

static int sc_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    return ct_py_nargs(name, nargs, want);
}

/* ------------------------------------------------------------ SchepersCore */
/* the float64 arrays bound, in this order, with their sizes (N: nx, C: nc) */
enum { SC_P3, SC_V, SC_R, SC_BA, SC_BG, SC_F3, SC_W, SC_AP, SC_GP, SC_PP, SC_FF, SC_TT, SC_Q, SC_FC, SC_PC, SC_TC,
       SC_QC, SC_E, SC_R2, SC_DR, SC_FREF, SC_CLP, SC_CLR, SC_TPB, SC_TPT, SC_ND };
static const char *sc_names[SC_ND] = {"p", "v", "R", "ba", "bg", "f", "w", "acc_prev", "gyr_prev", "P", "F", "T",
                                      "q", "Fc", "Pc", "Tc", "qc", "E", "R2", "dR", "fref", "clone_p", "clone_R",
                                      "TP", "TPT"};

typedef struct {
    PyObject_HEAD
    struct ct_sc s;
    Py_buffer views[SC_ND + 3];
    int nviews;
} SchepersCoreObject;

static void SchepersCore_release(SchepersCoreObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void SchepersCore_dealloc(SchepersCoreObject *self)
{
    SchepersCore_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static Py_ssize_t sc_len(int i, Py_ssize_t nx, Py_ssize_t nc)
{
    switch (i) {
    case SC_R: case SC_E: case SC_R2: case SC_DR:
        return 9;
    case SC_PP: case SC_FF: case SC_TT:
        return nx * nx;
    case SC_Q:
        return nx;
    case SC_FC: case SC_PC: case SC_TC:
        return CT_SC_CORE * CT_SC_CORE;
    case SC_QC:
        return CT_SC_CORE;
    case SC_CLP:
        return nc * 3;
    case SC_CLR:
        return nc * 9;
    case SC_TPB:
        return 6 * nx;
    case SC_TPT:
        return 36;
    default:
        return 3;
    }
}

/* SchepersCore(nx, nc, arrays, clone_t, clone_due, clone_taken, cp, co, qa, qpos, qg, qba, qbg) */
static int SchepersCore_init(SchepersCoreObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"nx", "nc", "arrays", "clone_t", "clone_due", "clone_taken", "cp", "co", "qa",
                             "qpos", "qg", "qba", "qbg", NULL};
    PyObject *arrays, *ct, *cd, *ck, *cp, *co;
    double *ptr[SC_ND];
    int nx, nc, i;
    struct ct_sc *s = &self->s;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiO!OOOO!O!ddddd", kwlist, &nx, &nc, &PyTuple_Type, &arrays, &ct,
                                     &cd, &ck, &PyTuple_Type, &cp, &PyTuple_Type, &co, &s->qa, &s->qpos, &s->qg,
                                     &s->qba, &s->qbg))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SchepersCore: already bound");
        return -1;
    }
    if (nc < 0 || nc > CT_SC_MAX_CLONES || nx < CT_SC_CORE + 6 * nc || nx > 256 || PyTuple_GET_SIZE(arrays) != SC_ND ||
        PyTuple_GET_SIZE(cp) != nc || PyTuple_GET_SIZE(co) != nc) {
        PyErr_Format(PyExc_ValueError, "SchepersCore: nc in 0..%d, nx in 15+6nc..256, %d arrays and nc clone rows",
                     CT_SC_MAX_CLONES, SC_ND);
        return -1;
    }
    for (i = 0; i < nc; ++i) {
        long a, b;
        if (sc_int(PyTuple_GET_ITEM(cp, i), CT_SC_CORE, nx - 3, &a, "cp") < 0 ||
            sc_int(PyTuple_GET_ITEM(co, i), CT_SC_CORE, nx - 3, &b, "co") < 0)
            return -1;
        s->cp[i] = (int)a;
        s->co[i] = (int)b;
    }
    for (i = 0; i < SC_ND; ++i) {
        if (sc_doubles(PyTuple_GET_ITEM(arrays, i), sc_len(i, nx, nc), i != SC_FREF, &self->views[i], sc_names[i]) < 0) {
            SchepersCore_release(self);
            return -1;
        }
        self->nviews = i + 1;
        ptr[i] = (double *)self->views[i].buf;
    }
    if (sc_get(ct, nc, 'q', 8, 0, &self->views[SC_ND], "clone_t") < 0) {
        SchepersCore_release(self);
        return -1;
    }
    self->nviews = SC_ND + 1;
    if (sc_get(cd, nc, '?', 1, 1, &self->views[SC_ND + 1], "clone_due") < 0) {
        SchepersCore_release(self);
        return -1;
    }
    self->nviews = SC_ND + 2;
    if (sc_get(ck, nc, '?', 1, 1, &self->views[SC_ND + 2], "clone_taken") < 0) {
        SchepersCore_release(self);
        return -1;
    }
    self->nviews = SC_ND + 3;
    s->nx = nx;
    s->nc = nc;
    s->p = ptr[SC_P3];
    s->v = ptr[SC_V];
    s->R = ptr[SC_R];
    s->ba = ptr[SC_BA];
    s->bg = ptr[SC_BG];
    s->f = ptr[SC_F3];
    s->w = ptr[SC_W];
    s->acc_prev = ptr[SC_AP];
    s->gyr_prev = ptr[SC_GP];
    s->P = ptr[SC_PP];
    s->F = ptr[SC_FF];
    s->T = ptr[SC_TT];
    s->q = ptr[SC_Q];
    s->Fc = ptr[SC_FC];
    s->Pc = ptr[SC_PC];
    s->Tc = ptr[SC_TC];
    s->qc = ptr[SC_QC];
    s->E = ptr[SC_E];
    s->R2 = ptr[SC_R2];
    s->dR = ptr[SC_DR];
    s->fref = ptr[SC_FREF];
    s->cl_p = ptr[SC_CLP];
    s->cl_R = ptr[SC_CLR];
    s->TP = ptr[SC_TPB];
    s->TPT = ptr[SC_TPT];
    s->cl_t = (int64_t *)self->views[SC_ND].buf;
    s->cl_due = (uint8_t *)self->views[SC_ND + 1].buf;
    s->cl_taken = (uint8_t *)self->views[SC_ND + 2].buf;
    s->steps = 0;
    return 0;
}

static int sc_ready(SchepersCoreObject *self)
{
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SchepersCore: not bound");
        return -1;
    }
    return 0;
}

/* propagate(t0, t_us, acc, gyr, initialized) */
static PyObject *SchepersCore_propagate(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long t0, t1;
    double acc[3], gyr[3];
    int init;
    if (sc_ready(self) < 0 || sc_nargs("propagate", nargs, 5) < 0)
        return NULL;
    t0 = PyLong_AsLongLong(args[0]);
    t1 = PyLong_AsLongLong(args[1]);
    if (PyErr_Occurred())
        return NULL;
    if (sc_copy_doubles(args[2], 3, acc, "acc") < 0 || sc_copy_doubles(args[3], 3, gyr, "gyr") < 0)
        return NULL;
    if ((init = PyObject_IsTrue(args[4])) < 0)
        return NULL;
    if (t1 <= t0) {
        PyErr_SetString(PyExc_ValueError, "propagate: t_us must be after the filter's time");
        return NULL;
    }
    ct_sc_propagate(&self->s, (int64_t)t0, (int64_t)t1, acc, gyr, init);
    Py_RETURN_NONE;
}

/* step(dt, initialized) */
static PyObject *SchepersCore_step(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double dt;
    int init;
    if (sc_ready(self) < 0 || sc_nargs("step", nargs, 2) < 0 || sc_double(args[0], &dt) < 0)
        return NULL;
    if ((init = PyObject_IsTrue(args[1])) < 0)
        return NULL;
    ct_sc_step(&self->s, dt, init);
    Py_RETURN_NONE;
}

/* build_F(F, q, dt): F a square float64 array (n x n, n >= 15) of any strides' owner, q >= 15 */
static PyObject *SchepersCore_build_F(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer fv, qv;
    double dt;
    Py_ssize_t n;
    if (sc_ready(self) < 0 || sc_nargs("build_F", nargs, 3) < 0 || sc_double(args[2], &dt) < 0)
        return NULL;
    if (sc_doubles(args[0], CT_SC_CORE * CT_SC_CORE, 1, &fv, "F") < 0)
        return NULL;
    if (fv.ndim != 2 || fv.shape[0] != fv.shape[1] || fv.shape[0] < CT_SC_CORE) {
        PyBuffer_Release(&fv);
        PyErr_SetString(PyExc_TypeError, "F: needs a square (n, n) float64 array, n >= 15");
        return NULL;
    }
    n = fv.shape[0];
    if (sc_doubles(args[1], CT_SC_CORE, 1, &qv, "q") < 0) {
        PyBuffer_Release(&fv);
        return NULL;
    }
    ct_sc_build_F(&self->s, (double *)fv.buf, (int)n, (double *)qv.buf, dt);
    PyBuffer_Release(&qv);
    PyBuffer_Release(&fv);
    Py_RETURN_NONE;
}

/* predict_pose(T, n, P6, pp) */
static PyObject *SchepersCore_predict_pose(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv, ppv;
    double T;
    long n;
    if (sc_ready(self) < 0 || sc_nargs("predict_pose", nargs, 4) < 0 || sc_double(args[0], &T) < 0 ||
        sc_int(args[1], 1, 1L << 30, &n, "steps") < 0)
        return NULL;
    if (sc_doubles(args[2], 36, 1, &pv, "P6") < 0)
        return NULL;
    if (sc_doubles(args[3], 3, 1, &ppv, "pp") < 0) {
        PyBuffer_Release(&pv);
        return NULL;
    }
    ct_sc_predict_pose(&self->s, T, (int)n, (double *)pv.buf, (double *)ppv.buf);
    PyBuffer_Release(&ppv);
    PyBuffer_Release(&pv);
    Py_RETURN_NONE;
}

/* take_clone(k, initialized), release_clone(k) */
static PyObject *SchepersCore_take_clone(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long k;
    int init;
    if (sc_ready(self) < 0 || sc_nargs("take_clone", nargs, 2) < 0 || sc_int(args[0], 0, self->s.nc - 1, &k, "k") < 0)
        return NULL;
    if ((init = PyObject_IsTrue(args[1])) < 0)
        return NULL;
    ct_sc_take_clone(&self->s, (int)k, init);
    Py_RETURN_NONE;
}

/* back_clone(k, dt, G, initialized) */
static PyObject *SchepersCore_back_clone(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long k;
    double dt, G[9];
    int init;
    if (sc_ready(self) < 0 || sc_nargs("back_clone", nargs, 4) < 0 || sc_int(args[0], 0, self->s.nc - 1, &k, "k") < 0 ||
        sc_double(args[1], &dt) < 0 || sc_copy_doubles(args[2], 9, G, "G") < 0)
        return NULL;
    if ((init = PyObject_IsTrue(args[3])) < 0)
        return NULL;
    ct_sc_back_clone(&self->s, (int)k, dt, G, init, self->s.TP, self->s.TPT);
    Py_RETURN_NONE;
}

static PyObject *SchepersCore_release_clone(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long k;
    if (sc_ready(self) < 0 || sc_nargs("release_clone", nargs, 1) < 0 ||
        sc_int(args[0], 0, self->s.nc - 1, &k, "k") < 0)
        return NULL;
    ct_sc_release_clone(&self->s, (int)k);
    Py_RETURN_NONE;
}

/* inject(dx) */
static PyObject *SchepersCore_inject(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer dv;
    if (sc_ready(self) < 0 || sc_nargs("inject", nargs, 1) < 0)
        return NULL;
    if (sc_doubles(args[0], self->s.nx, 0, &dv, "dx") < 0)
        return NULL;
    ct_sc_inject(&self->s, (const double *)dv.buf);
    PyBuffer_Release(&dv);
    Py_RETURN_NONE;
}

/* pose_values(out): a POSE's 14 values */
static PyObject *SchepersCore_pose_values(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer ov;
    if (sc_ready(self) < 0 || sc_nargs("pose_values", nargs, 1) < 0)
        return NULL;
    if (sc_doubles(args[0], 14, 1, &ov, "out") < 0)
        return NULL;
    ct_sc_pose_values(&self->s, (double *)ov.buf);
    PyBuffer_Release(&ov);
    Py_RETURN_NONE;
}

/* steps(): the strapdown steps taken (SchepersEKF._steps) */
static PyObject *SchepersCore_steps(SchepersCoreObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (sc_ready(self) < 0 || sc_nargs("steps", nargs, 0) < 0)
        return NULL;
    return PyLong_FromLongLong((long long)self->s.steps);
}

#define SC_METH(name, doc) {#name, (PyCFunction)(void (*)(void))SchepersCore_##name, METH_FASTCALL, doc}
static PyMethodDef SchepersCore_methods[] = {
    SC_METH(propagate, "propagate(t0, t_us, acc, gyr, initialized): SchepersEKF.propagate from t0 < t_us"),
    SC_METH(step, "step(dt, initialized): SchepersEKF._step"),
    SC_METH(build_F, "build_F(F, q, dt): SchepersEKF._build_F into a square F and q"),
    SC_METH(predict_pose, "predict_pose(T, steps, P6, pp): SchepersEKF.predict_pose over T seconds"),
    SC_METH(take_clone, "take_clone(k, initialized): PoseClones.take"),
    SC_METH(release_clone, "release_clone(k): PoseClones.release"),
    SC_METH(back_clone, "back_clone(k, dt, G, initialized): PoseClones.back"),
    SC_METH(inject, "inject(dx): SchepersEKF._inject with PoseClones.inject"),
    SC_METH(pose_values, "pose_values(out): SchepersEKF.pose_values into out (14)"),
    SC_METH(steps, "steps(): the strapdown steps taken"),
    {NULL, NULL, 0, NULL}};

static PyTypeObject SchepersCoreType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SchepersCore",
    .tp_basicsize = sizeof(SchepersCoreObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SchepersCore(nx, nc, arrays, clone_t, clone_due, clone_taken, cp, co, qa, qpos, qg, qba, qbg): "
              "one single-coil EKF's kernels bound to its arrays (estimate.single_coil)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SchepersCore_init,
    .tp_dealloc = (destructor)SchepersCore_dealloc,
    .tp_methods = SchepersCore_methods,
};

/* ---------------------------------------------------- SingleCoilUpdateCore */
enum { SU_H, SU_R, SU_Y, SU_UDX, SU_PHT, SU_S, SU_YP, SU_P0, SU_PPREV, SU_DX, SU_PI, SU_RI, SU_HDX, SU_DR, SU_ST,
       SU_N };
static const char *su_names[SU_N] = {"H", "R", "y", "udx", "PHt", "S", "y_pred", "P0", "Pprev", "dx", "pi", "Ri",
                                     "Hdx", "dR", "st"};

/* the most coils a bound run evaluates (_coremodule.c's Signal takes as many) */
#define SU_MAX_COILS 64

/* bind_run's buffers: the shared KalmanUpdate's (ct_kalman), the model's geometry, B, J, h, H and
 * centres, and the run's outputs rs (SU_RS) */
enum { SR_KH, SR_KR, SR_KY, SR_KDX, SR_KS, SR_KSI, SR_KK, SR_KPHT, SR_KT, SR_KTH, SR_KX, SR_KKR, SR_KW, SR_KL, SR_KM,
       SR_GEOM, SR_B, SR_J, SR_H, SR_HH, SR_C, SR_RS, SR_N };
/* rs[]: a run's outputs: updates applied, rejected, the first pass's NIS, the last pass's, the
 * model's evaluations */
enum { SU_RS_APPLIED, SU_RS_REJECTED, SU_RS_NIS, SU_RS_NIS_LAST, SU_RS_EVALS, SU_RS_N };

typedef struct {
    PyObject_HEAD
    struct ct_scu u;
    Py_buffer views[SU_N];
    int nviews;
    struct ct_kalman k;                /* the shared update's buffers (bind_run) */
    const double *geom, *centres;
    double *B, *J, *h, *H, *rs;
    int ncoils, sym_every;
    Py_buffer rviews[SR_N];
    int nrviews;
} SCUpdateObject;

static void SCUpdate_release(SCUpdateObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    while (self->nrviews > 0)
        PyBuffer_Release(&self->rviews[--self->nrviews]);
}

static void SCUpdate_dealloc(SCUpdateObject *self)
{
    SCUpdate_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* SingleCoilUpdateCore(nx, arrays) */
static int SCUpdate_init(SCUpdateObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"nx", "arrays", NULL};
    PyObject *arrays;
    double *ptr[SU_N];
    int nx, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iO!", kwlist, &nx, &PyTuple_Type, &arrays))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SingleCoilUpdateCore: already bound");
        return -1;
    }
    if (nx < CT_SC_CORE || nx > 256 || PyTuple_GET_SIZE(arrays) != SU_N) {
        PyErr_Format(PyExc_ValueError, "SingleCoilUpdateCore: nx in 15..256 and %d arrays", SU_N);
        return -1;
    }
    for (i = 0; i < SU_N; ++i) {
        Py_ssize_t len;
        switch (i) {
        case SU_H: case SU_PHT: len = 3 * (Py_ssize_t)nx; break;
        case SU_R: case SU_S: case SU_RI: case SU_DR: len = 9; break;
        case SU_UDX: case SU_DX: len = nx; break;
        case SU_P0: case SU_PPREV: len = (Py_ssize_t)nx * nx; break;
        case SU_ST: len = CT_SCU_NST; break;
        default: len = 3;
        }
        if (sc_doubles(PyTuple_GET_ITEM(arrays, i), len, i != SU_UDX, &self->views[i], su_names[i]) < 0) {
            SCUpdate_release(self);
            return -1;
        }
        self->nviews = i + 1;
        ptr[i] = (double *)self->views[i].buf;
    }
    self->u.nx = nx;
    self->u.H = ptr[SU_H];
    self->u.R = ptr[SU_R];
    self->u.y = ptr[SU_Y];
    self->u.udx = ptr[SU_UDX];
    self->u.PHt = ptr[SU_PHT];
    self->u.S = ptr[SU_S];
    self->u.y_pred = ptr[SU_YP];
    self->u.P0 = ptr[SU_P0];
    self->u.Pprev = ptr[SU_PPREV];
    self->u.dx = ptr[SU_DX];
    self->u.pi = ptr[SU_PI];
    self->u.Ri = ptr[SU_RI];
    self->u.Hdx = ptr[SU_HDX];
    self->u.dR = ptr[SU_DR];
    self->u.st = ptr[SU_ST];
    return 0;
}

static int su_ready(SCUpdateObject *self)
{
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "SingleCoilUpdateCore: not bound");
        return -1;
    }
    return 0;
}

/* the coil's rows of the model (h (n, 3), H (n, 3, 6), centres (n, 3)) into m; views released by
 * the caller (3 of them, in hv) */
static int su_model(PyObject *h, PyObject *H, PyObject *centres, long coil, Py_buffer *hv, struct ct_scm *m)
{
    Py_ssize_t n;
    if (sc_doubles(h, 3, 0, &hv[0], "h") < 0)
        return -1;
    n = hv[0].len / (Py_ssize_t)(3 * sizeof(double));
    if (coil < 0 || coil >= n) {
        PyBuffer_Release(&hv[0]);
        PyErr_Format(PyExc_ValueError, "coil must be in 0..%zd, got %ld", n - 1, coil);
        return -1;
    }
    if (sc_doubles(H, 18 * n, 0, &hv[1], "H") < 0) {
        PyBuffer_Release(&hv[0]);
        return -1;
    }
    if (centres != NULL && sc_doubles(centres, 3 * n, 0, &hv[2], "centres") < 0) {
        PyBuffer_Release(&hv[0]);
        PyBuffer_Release(&hv[1]);
        return -1;
    }
    m->h = (const double *)hv[0].buf + 3 * coil;
    m->Hu = (const double *)hv[1].buf + 18 * coil;
    m->centre = centres != NULL ? (const double *)hv[2].buf + 3 * coil : NULL;
    return 0;
}

static void su_model_release(Py_buffer *hv, int with_centres)
{
    PyBuffer_Release(&hv[0]);
    PyBuffer_Release(&hv[1]);
    if (with_centres)
        PyBuffer_Release(&hv[2]);
}

/* the clone rows cp, co of an nx-state filter */
static int su_rows(SCUpdateObject *self, PyObject *a, PyObject *b, long *cp, long *co)
{
    return (sc_int(a, 0, self->u.nx - 3, cp, "cp") < 0 || sc_int(b, 0, self->u.nx - 3, co, "co") < 0) ? -1 : 0;
}

/* the optional coil gain (row, current) of begin and again: args[at], args[at + 1] when given */
static int su_gain(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs, Py_ssize_t at, struct ct_scm *m)
{
    long g;
    m->gain = -1;
    m->gain_current = 0.0;
    if (nargs == at)
        return 0;
    if (sc_int(args[at], -1, self->u.nx - 1, &g, "gain") < 0 || sc_double(args[at + 1], &m->gain_current) < 0)
        return -1;
    m->gain = (int)g;
    return 0;
}

/* begin(P, p, R, cp, co, h, H, centres, coil, y, var, current, rel_model, r_scale[, gain, gain_current]) */
static PyObject *SCUpdate_begin(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv, hv[3];
    double p[3], R[9], y[3], var[3];
    long cp, co, coil;
    struct ct_scm m;
    if (su_ready(self) < 0 || sc_nargs("begin", nargs, nargs == 16 ? 16 : 14) < 0 ||
        su_rows(self, args[3], args[4], &cp, &co) < 0 || sc_int(args[8], 0, 1L << 20, &coil, "coil") < 0 ||
        su_gain(self, args, nargs, 14, &m) < 0)
        return NULL;
    if (sc_copy_doubles(args[1], 3, p, "p") < 0 || sc_copy_doubles(args[2], 9, R, "R") < 0 ||
        sc_copy_doubles(args[9], 3, y, "y") < 0 || sc_copy_doubles(args[10], 3, var, "var") < 0 ||
        sc_double(args[11], &m.current) < 0 || sc_double(args[12], &m.rel_model) < 0 ||
        sc_double(args[13], &m.r_scale) < 0)
        return NULL;
    m.y = y;
    m.var = var;
    if (su_model(args[5], args[6], args[7], coil, hv, &m) < 0)
        return NULL;
    if (sc_doubles(args[0], (Py_ssize_t)self->u.nx * self->u.nx, 1, &pv, "P") < 0) {
        su_model_release(hv, 1);
        return NULL;
    }
    ct_scu_begin(&self->u, (double *)pv.buf, p, R, (int)cp, (int)co, &m);
    PyBuffer_Release(&pv);
    su_model_release(hv, 1);
    Py_RETURN_NONE;
}

/* again(it, P, cp, co, h, H, coil, y, current[, gain, gain_current]): y_pred and pass it (> 0) at the
 * model just evaluated */
static PyObject *SCUpdate_again(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv, hv[3];
    double y[3];
    long it, cp, co, coil;
    struct ct_scm m;
    if (su_ready(self) < 0 || sc_nargs("again", nargs, nargs == 11 ? 11 : 9) < 0 ||
        sc_int(args[0], 1, 1L << 20, &it, "it") < 0 || su_rows(self, args[2], args[3], &cp, &co) < 0 ||
        sc_int(args[6], 0, 1L << 20, &coil, "coil") < 0 || su_gain(self, args, nargs, 9, &m) < 0)
        return NULL;
    if (sc_copy_doubles(args[7], 3, y, "y") < 0 || sc_double(args[8], &m.current) < 0)
        return NULL;
    m.y = y;
    m.var = NULL;
    m.rel_model = 0.0;
    m.r_scale = 1.0;
    if (su_model(args[4], args[5], NULL, coil, hv, &m) < 0)
        return NULL;
    if (sc_doubles(args[1], (Py_ssize_t)self->u.nx * self->u.nx, 1, &pv, "P") < 0) {
        su_model_release(hv, 0);
        return NULL;
    }
    ct_scu_predict(&self->u, &m);
    ct_scu_pass(&self->u, (int)it, (double *)pv.buf, (int)cp, (int)co, &m);
    PyBuffer_Release(&pv);
    su_model_release(hv, 0);
    Py_RETURN_NONE;
}

/* after(it, flags, iterations, P, p, R, cp, co, var) -> bool: another pass follows */
static PyObject *SCUpdate_after(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    double p[3], R[9], var[3];
    long it, flags, iters, cp, co;
    int more;
    if (su_ready(self) < 0 || sc_nargs("after", nargs, 9) < 0 || sc_int(args[0], 0, 1L << 20, &it, "it") < 0 ||
        sc_int(args[1], 0, 1L << 20, &flags, "flags") < 0 || sc_int(args[2], 1, 1L << 20, &iters, "iterations") < 0 ||
        su_rows(self, args[6], args[7], &cp, &co) < 0)
        return NULL;
    if (sc_copy_doubles(args[4], 3, p, "p") < 0 || sc_copy_doubles(args[5], 9, R, "R") < 0 ||
        sc_copy_doubles(args[8], 3, var, "var") < 0)
        return NULL;
    if (sc_doubles(args[3], (Py_ssize_t)self->u.nx * self->u.nx, 1, &pv, "P") < 0)
        return NULL;
    more = ct_scu_after(&self->u, (int)it, (int)flags, (int)iters, (double *)pv.buf, p, R, (int)cp, (int)co, var);
    PyBuffer_Release(&pv);
    return PyBool_FromLong(more);
}

/* bind_run(kalman, model, rs, sym_every): kalman = the shared KalmanUpdate's (H, R, y, dx, S, Sinv, K, PHt,
 * T, TH, X, KR, w, L, M), model = the SingleCoilModel's (geom, B, J, h, H, centres) */
static PyObject *SCUpdate_bind_run(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double *ptr[SR_N];
    Py_ssize_t nx, nc;
    long every;
    int i;
    if (su_ready(self) < 0 || sc_nargs("bind_run", nargs, 4) < 0 ||
        sc_int(args[3], 1, 1L << 20, &every, "sym_every") < 0)
        return NULL;
    if (self->nrviews) {
        PyErr_SetString(PyExc_RuntimeError, "SingleCoilUpdateCore: run already bound");
        return NULL;
    }
    if (!PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != SR_GEOM || !PyTuple_Check(args[1]) ||
        PyTuple_GET_SIZE(args[1]) != SR_RS - SR_GEOM) {
        PyErr_Format(PyExc_TypeError, "bind_run: %d kalman arrays and %d model arrays", (int)SR_GEOM,
                     (int)(SR_RS - SR_GEOM));
        return NULL;
    }
    nx = self->u.nx;
    {
        PyObject *g = PyTuple_GET_ITEM(args[1], 0);
        Py_buffer gv;
        if (sc_doubles(g, CT_COIL_STRIDE, 0, &gv, "geom") < 0)
            return NULL;
        nc = gv.len / (Py_ssize_t)(CT_COIL_STRIDE * sizeof(double));
        PyBuffer_Release(&gv);
        if (nc < 1 || nc > SU_MAX_COILS) {
            PyErr_Format(PyExc_ValueError, "bind_run: 1..%d coils", SU_MAX_COILS);
            return NULL;
        }
    }
    for (i = 0; i < SR_N; ++i) {
        static const char *names[SR_N] = {"H", "R", "y", "dx", "S", "Sinv", "K", "PHt", "T", "TH", "X", "KR", "w",
                                          "L", "M", "geom", "B", "J", "h", "H", "centres", "rs"};
        PyObject *o = i < SR_GEOM ? PyTuple_GET_ITEM(args[0], i)
                      : i < SR_RS ? PyTuple_GET_ITEM(args[1], i - SR_GEOM) : args[2];
        Py_ssize_t len;
        switch (i) {
        case SR_KH: case SR_KK: case SR_KPHT: case SR_KTH: case SR_KKR: len = 3 * nx; break;
        case SR_KDX: len = nx; break;
        case SR_KT: case SR_KX: len = nx * nx; break;
        case SR_KY: case SR_KW: len = 3; break;
        case SR_GEOM: len = CT_COIL_STRIDE * nc; break;
        case SR_B: case SR_H: case SR_C: len = 3 * nc; break;
        case SR_J: len = 9 * nc; break;
        case SR_HH: len = 18 * nc; break;
        case SR_RS: len = SU_RS_N; break;
        default: len = 9;
        }
        if (sc_doubles(o, len, i != SR_KH && i != SR_KR && i != SR_KY && i != SR_GEOM && i != SR_C, &self->rviews[i],
                       names[i]) < 0) {
            while (self->nrviews > 0)
                PyBuffer_Release(&self->rviews[--self->nrviews]);
            return NULL;
        }
        self->nrviews = i + 1;
        ptr[i] = (double *)self->rviews[i].buf;
    }
    if (ptr[SR_KH] != self->u.H || ptr[SR_KR] != self->u.R || ptr[SR_KY] != self->u.y || ptr[SR_KDX] != self->u.udx) {
        while (self->nrviews > 0)
            PyBuffer_Release(&self->rviews[--self->nrviews]);
        PyErr_SetString(PyExc_ValueError, "bind_run: H, R, y, dx must be the ones this update was bound to");
        return NULL;
    }
    self->k.n = (int)nx;
    self->k.m = 3;
    self->k.H = ptr[SR_KH];
    self->k.R = ptr[SR_KR];
    self->k.y = ptr[SR_KY];
    self->k.dx = ptr[SR_KDX];
    self->k.S = ptr[SR_KS];
    self->k.Sinv = ptr[SR_KSI];
    self->k.K = ptr[SR_KK];
    self->k.PHt = ptr[SR_KPHT];
    self->k.T = ptr[SR_KT];
    self->k.TH = ptr[SR_KTH];
    self->k.X = ptr[SR_KX];
    self->k.KR = ptr[SR_KKR];
    self->k.w = ptr[SR_KW];
    self->k.L = ptr[SR_KL];
    self->k.M = ptr[SR_KM];
    self->geom = ptr[SR_GEOM];
    self->B = ptr[SR_B];
    self->J = ptr[SR_J];
    self->h = ptr[SR_H];
    self->H = ptr[SR_HH];
    self->centres = ptr[SR_C];
    self->rs = ptr[SR_RS];
    self->ncoils = (int)nc;
    self->sym_every = (int)every;
    Py_RETURN_NONE;
}

/* SingleCoilModel.evaluate (SignalModel.measure at 1 A per coil, no distortion map) at (p, R) */
static void su_evaluate(SCUpdateObject *self, const double *p, const double *R)
{
    double ones[SU_MAX_COILS];
    int j;
    for (j = 0; j < self->ncoils; ++j)
        ones[j] = 1.0;
    ct_signal_fields(self->geom, self->ncoils, p[0], p[1], p[2], ones, 1, self->B, self->J);
    ct_signal_project_jac(self->ncoils, R, self->B, self->J, self->h, self->H);
    self->rs[SU_RS_EVALS] += 1.0;
}

/* KalmanUpdate._update_compiled: the update with its bookkeeping (count, rejected), P symmetrised
 * every sym_every-th applied update as ekf.symmetrize does ((P + P^T) * 0.5 through T) */
static int su_kalman(SCUpdateObject *self, double *P, double gate, long long *count, double *nis)
{
    int flags = ct_kalman_update(&self->k, P, gate, nis), n = self->k.n, i, j;
    double *T = self->k.T;
    if (flags != CT_EKF_OK) {
        self->rs[SU_RS_REJECTED] += 1.0;
        return flags;
    }
    self->rs[SU_RS_APPLIED] += 1.0;
    *count += 1;
    if (*count % self->sym_every == 0) {
        memcpy(T, P, (size_t)n * n * sizeof(double));
        for (i = 0; i < n; ++i)
            for (j = 0; j < n; ++j)
                P[i * n + j] = (T[i * n + j] + T[j * n + i]) * 0.5;
    }
    return flags;
}

/* SCUpdate_run's work on its values: the model's evaluations, the passes, the shared update's (rs:
 * the counts, the NISs, the evaluations); p, R the linearisation pose (copied: the passes may move
 * the clone they are read from), y, var the amplitude and its variances; m's current, rel_model,
 * r_scale, gain and gain_current set by the caller; the flags of the first pass */
static int su_run(SCUpdateObject *self, double *P, const double *p0, const double *R0, long cp, long co, long coil,
                  const double *y0, const double *var0, struct ct_scm *m, double gate, long iters, long long count)
{
    double p[3], R[9], y[3], var[3], nis;
    int flags, f, it;
    memcpy(p, p0, sizeof p);
    memcpy(R, R0, sizeof R);
    memcpy(y, y0, sizeof y);
    memcpy(var, var0, sizeof var);
    m->y = y;
    m->var = var;
    m->h = self->h + 3 * coil;
    m->Hu = self->H + 18 * coil;
    m->centre = self->centres + 3 * coil;
    memset(self->rs, 0, SU_RS_N * sizeof(double));
    su_evaluate(self, p, R);
    ct_scu_begin(&self->u, P, p, R, (int)cp, (int)co, m);
    flags = su_kalman(self, P, gate, &count, &nis);
    self->rs[SU_RS_NIS] = nis;
    self->rs[SU_RS_NIS_LAST] = nis;
    if (!(flags & (CT_EKF_GATED | CT_EKF_NOT_PD | CT_EKF_NONFINITE))) {
        f = flags;
        it = 0;
        /* the later passes' model: no amplitude variances, no noise terms (SCUpdate_again) */
        while (ct_scu_after(&self->u, it, f, (int)iters, P, p, R, (int)cp, (int)co, var)) {
            struct ct_scm ma = *m;
            ++it;
            su_evaluate(self, self->u.pi, self->u.Ri);
            ma.var = NULL;
            ma.rel_model = 0.0;
            ma.r_scale = 1.0;
            ma.centre = NULL;
            ct_scu_predict(&self->u, &ma);
            ct_scu_pass(&self->u, it, P, (int)cp, (int)co, &ma);
            f = su_kalman(self, P, HUGE_VAL, &count, &nis);
            self->rs[SU_RS_NIS_LAST] = nis;
        }
    }
    return flags;
}

/* run(P, p, R, cp, co, coil, y, var, current, rel_model, r_scale, gate, iterations, count[, gain,
 * gain_current]) -> flags: SingleCoilUpdate._run_compiled in one call (the model's evaluations, the
 * passes, the shared update's); rs: the counts, the NISs, the evaluations */
static PyObject *SCUpdate_run(SCUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    double p[3], R[9], y[3], var[3], gate;
    long cp, co, coil, iters;
    long long count;
    struct ct_scm m;
    int flags;
    if (su_ready(self) < 0 || sc_nargs("run", nargs, nargs == 16 ? 16 : 14) < 0)
        return NULL;
    if (!self->nrviews) {
        PyErr_SetString(PyExc_RuntimeError, "SingleCoilUpdateCore: run not bound");
        return NULL;
    }
    if (su_rows(self, args[3], args[4], &cp, &co) < 0 || sc_int(args[5], 0, self->ncoils - 1, &coil, "coil") < 0 ||
        sc_int(args[12], 1, 1L << 20, &iters, "iterations") < 0 || su_gain(self, args, nargs, 14, &m) < 0)
        return NULL;
    count = PyLong_AsLongLong(args[13]);
    if (count == -1 && PyErr_Occurred())
        return NULL;
    if (sc_copy_doubles(args[1], 3, p, "p") < 0 || sc_copy_doubles(args[2], 9, R, "R") < 0 ||
        sc_copy_doubles(args[6], 3, y, "y") < 0 || sc_copy_doubles(args[7], 3, var, "var") < 0 ||
        sc_double(args[8], &m.current) < 0 || sc_double(args[9], &m.rel_model) < 0 ||
        sc_double(args[10], &m.r_scale) < 0 || sc_double(args[11], &gate) < 0)
        return NULL;
    if (sc_doubles(args[0], (Py_ssize_t)self->u.nx * self->u.nx, 1, &pv, "P") < 0)
        return NULL;
    flags = su_run(self, (double *)pv.buf, p, R, cp, co, coil, y, var, &m, gate, iters, count);
    PyBuffer_Release(&pv);
    return PyLong_FromLong(flags);
}

#define SU_METH(name, doc) {#name, (PyCFunction)(void (*)(void))SCUpdate_##name, METH_FASTCALL, doc}
static PyMethodDef SCUpdate_methods[] = {
    SU_METH(begin, "begin(P, p, R, cp, co, h, H, centres, coil, y, var, current, rel_model, r_scale[, gain, "
                   "gain_current]): "
                   "SingleCoilUpdate.run up to the first pass's shared update"),
    SU_METH(again, "again(it, P, cp, co, h, H, coil, y, current[, gain, gain_current]): pass it up to its shared "
                   "update"),
    SU_METH(after, "after(it, flags, iterations, P, p, R, cp, co, var) -> bool: keep pass it, another pass?"),
    SU_METH(bind_run, "bind_run(kalman, model, rs, sym_every): the shared update's and the model's buffers, for run"),
    SU_METH(run, "run(P, p, R, cp, co, coil, y, var, current, rel_model, r_scale, gate, iterations, count[, gain, "
                 "gain_current]) -> flags: SingleCoilUpdate.run in one call (its outputs in rs)"),
    {NULL, NULL, 0, NULL}};

static PyTypeObject SCUpdateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SingleCoilUpdateCore",
    .tp_basicsize = sizeof(SCUpdateObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SingleCoilUpdateCore(nx, arrays): the single-coil update's passes bound to its buffers "
              "(estimate.single_coil_update)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SCUpdate_init,
    .tp_dealloc = (destructor)SCUpdate_dealloc,
    .tp_methods = SCUpdate_methods,
};

/* ---------------------------------------------------------- FixedRefCore */
/* accuracy.FixedCycleReference's buffers (and MeanBudgetReference's own, or None) */
enum { RF_P, RF_F, RF_Q, RF_T, RF_AVG, RF_LAW, RF_ST, RF_OWN, RF_N };
static const char *rf_names[RF_N] = {"P", "F", "q", "T", "avg", "law", "st", "own"};
static const Py_ssize_t rf_len[RF_N] = {CT_SC_CORE * CT_SC_CORE, CT_SC_CORE * CT_SC_CORE, CT_SC_CORE,
                                        CT_SC_CORE * CT_SC_CORE, 6, 2, CT_REF_NST, 2};

/* the pulse's update buffers (KalmanUpdate's H, R, y: bind_pulse) */
enum { RFP_H, RFP_R, RFP_Y, RFP_N };

typedef struct {
    PyObject_HEAD
    struct ct_scref r;
    Py_buffer views[RF_N];
    int nviews;
    Py_buffer pviews[RFP_N];
    int npviews, nx, pos, ori;
    double var_amp, rel_model, current_sigma;
} FixedRefObject;

static void FixedRef_release(FixedRefObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    while (self->npviews > 0)
        PyBuffer_Release(&self->pviews[--self->npviews]);
}

static void FixedRef_dealloc(FixedRefObject *self)
{
    FixedRef_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* FixedRefCore(arrays, own, warmup_us, avg_us, exp_pos, exp_ori): arrays = (P, F, q, T, avg, law, st) */
static int FixedRef_init(FixedRefObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"arrays", "own", "warmup_us", "avg_us", "exp_pos", "exp_ori", NULL};
    PyObject *arrays, *own;
    double *ptr[RF_N];
    int i;
    struct ct_scref *r = &self->r;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!Odddd", kwlist, &PyTuple_Type, &arrays, &own, &r->warmup_us,
                                     &r->avg_us, &r->exp[0], &r->exp[1]))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "FixedRefCore: already bound");
        return -1;
    }
    if (PyTuple_GET_SIZE(arrays) != RF_OWN) {
        PyErr_Format(PyExc_ValueError, "FixedRefCore: %d arrays", RF_OWN);
        return -1;
    }
    for (i = 0; i < RF_N; ++i) {
        PyObject *o = i < RF_OWN ? PyTuple_GET_ITEM(arrays, i) : own;
        ptr[i] = NULL;
        if (o == Py_None && i == RF_OWN)
            break;
        if (sc_doubles(o, rf_len[i], 1, &self->views[i], rf_names[i]) < 0) {
            FixedRef_release(self);
            return -1;
        }
        self->nviews = i + 1;
        ptr[i] = (double *)self->views[i].buf;
    }
    r->P = ptr[RF_P];
    r->F = ptr[RF_F];
    r->q = ptr[RF_Q];
    r->T = ptr[RF_T];
    r->avg = ptr[RF_AVG];
    r->law = ptr[RF_LAW];
    r->st = ptr[RF_ST];
    r->own = ptr[RF_OWN];
    return 0;
}

/* propagate(ekf_core, dt, dt_us, elapsed_us, mean_us, settled, settle_drop) */
static PyObject *FixedRef_propagate(FixedRefObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double dt, elapsed, mean, drop;
    int64_t dt_us;
    int settled;
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "FixedRefCore: not bound");
        return NULL;
    }
    if (sc_nargs("propagate", nargs, 7) < 0)
        return NULL;
    if (!PyObject_TypeCheck(args[0], &SchepersCoreType) || !((SchepersCoreObject *)args[0])->nviews) {
        PyErr_SetString(PyExc_TypeError, "propagate: ekf_core must be a bound SchepersCore");
        return NULL;
    }
    if (sc_double(args[1], &dt) < 0 || ct_py_int64(args[2], &dt_us) < 0 || sc_double(args[3], &elapsed) < 0 ||
        sc_double(args[4], &mean) < 0 || (settled = PyObject_IsTrue(args[5])) < 0 || sc_double(args[6], &drop) < 0)
        return NULL;
    ct_scp_ref_propagate(&((SchepersCoreObject *)args[0])->s, &self->r, dt, dt_us, elapsed, mean, settled, drop);
    Py_RETURN_NONE;
}

/* bind_pulse(H, R, y, nx, pos, ori, var_amp, rel_model, current_sigma): the pulse's update buffers
 * (H 3 x nx, R 3 x 3, y 3) and constants, once */
static PyObject *FixedRef_bind_pulse(FixedRefObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *names[RFP_N] = {"H", "R", "y"};
    long nx, pos, ori;
    int i;
    if (self->npviews) {
        PyErr_SetString(PyExc_RuntimeError, "FixedRefCore: pulse already bound");
        return NULL;
    }
    if (sc_nargs("bind_pulse", nargs, 9) < 0 || sc_int(args[3], 6, CT_SC_CORE, &nx, "nx") < 0 ||
        sc_int(args[4], 0, nx - 3, &pos, "pos") < 0 || sc_int(args[5], 0, nx - 3, &ori, "ori") < 0 ||
        sc_double(args[6], &self->var_amp) < 0 || sc_double(args[7], &self->rel_model) < 0 ||
        sc_double(args[8], &self->current_sigma) < 0)
        return NULL;
    for (i = 0; i < RFP_N; ++i) {
        Py_ssize_t n = i == RFP_H ? 3 * nx : (i == RFP_R ? 9 : 3);
        if (sc_doubles(args[i], n, 1, &self->pviews[i], names[i]) < 0) {
            while (self->npviews > 0)
                PyBuffer_Release(&self->pviews[--self->npviews]);
            return NULL;
        }
        self->npviews = i + 1;
    }
    self->nx = (int)nx;
    self->pos = (int)pos;
    self->ori = (int)ori;
    Py_RETURN_NONE;
}

/* pulse(h, H, coil, current): FixedCycleReference._pulse's H, R and y from the model's h (n x 3) and
 * H (n x 3 x 6) of coil `coil` at `current` (ct_scp_ref_pulse_fill) */
static PyObject *FixedRef_pulse(FixedRefObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vh, vH;
    long coil;
    double c;
    if (self->npviews != RFP_N) {
        PyErr_SetString(PyExc_RuntimeError, "FixedRefCore: pulse not bound");
        return NULL;
    }
    if (sc_nargs("pulse", nargs, 4) < 0 || sc_int(args[2], 0, 1L << 20, &coil, "coil") < 0 ||
        sc_double(args[3], &c) < 0)
        return NULL;
    if (sc_doubles(args[0], 3 * (coil + 1), 0, &vh, "h") < 0)
        return NULL;
    if (sc_doubles(args[1], 18 * (coil + 1), 0, &vH, "H") < 0) {
        PyBuffer_Release(&vh);
        return NULL;
    }
    ct_scp_ref_pulse_fill(self->nx, (double *)self->pviews[RFP_H].buf, (double *)self->pviews[RFP_R].buf,
                          (double *)self->pviews[RFP_Y].buf, (const double *)vH.buf + 18 * coil,
                          (const double *)vh.buf + 3 * coil, c, self->var_amp, self->rel_model,
                          self->current_sigma, self->pos, self->ori);
    PyBuffer_Release(&vH);
    PyBuffer_Release(&vh);
    Py_RETURN_NONE;
}

static PyMethodDef FixedRef_methods[] = {
    {"propagate", (PyCFunction)(void (*)(void))FixedRef_propagate, METH_FASTCALL,
     "propagate(ekf_core, dt, dt_us, elapsed_us, mean_us, settled, settle_drop): FixedCycleReference._propagate "
     "(and MeanBudgetReference's running mean); the scalars after it in st"},
    {"bind_pulse", (PyCFunction)(void (*)(void))FixedRef_bind_pulse, METH_FASTCALL,
     "bind_pulse(H, R, y, nx, pos, ori, var_amp, rel_model, current_sigma): the pulse's update buffers, once"},
    {"pulse", (PyCFunction)(void (*)(void))FixedRef_pulse, METH_FASTCALL,
     "pulse(h, H, coil, current): FixedCycleReference._pulse's H, R and y (the update is KalmanUpdate's)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FixedRefType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FixedRefCore",
    .tp_basicsize = sizeof(FixedRefObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FixedRefCore(arrays, own, warmup_us, avg_us, exp_pos, exp_ori): the fixed cycle's reference "
              "covariance propagation bound to its arrays (actuate.accuracy)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FixedRef_init,
    .tp_dealloc = (destructor)FixedRef_dealloc,
    .tp_methods = FixedRef_methods,
};

/* ------------------------------------------------------------ PolicyCore */
/* the decision model's h (n x 3), H (n x 3 x 6) and the limits (n) bound; the scratch of PoseCovUpdate */
typedef struct {
    PyObject_HEAD
    struct ct_scp_cov w;
    int n;
    const double *h, *H;
    double *lim;
    Py_buffer views[3];
    int nviews;
} PolicyObject;

static void Policy_release(PolicyObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void Policy_dealloc(PolicyObject *self)
{
    Policy_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* PolicyCore(n, h, H, lim) */
static int Policy_init(PolicyObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "h", "H", "lim", NULL};
    PyObject *h, *H, *lim;
    int n;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOO", kwlist, &n, &h, &H, &lim))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "PolicyCore: already bound");
        return -1;
    }
    if (n < 1 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "PolicyCore: n in 1..64");
        return -1;
    }
    if (sc_doubles(h, 3 * n, 0, &self->views[0], "h") < 0)
        return -1;
    self->nviews = 1;
    if (sc_doubles(H, 18 * n, 0, &self->views[1], "H") < 0 || (self->nviews = 2,
        sc_doubles(lim, n, 1, &self->views[2], "lim") < 0)) {
        Policy_release(self);
        return -1;
    }
    self->nviews = 3;
    self->n = n;
    self->h = (const double *)self->views[0].buf;
    self->H = (const double *)self->views[1].buf;
    self->lim = (double *)self->views[2].buf;
    return 0;
}

static int po_ready(PolicyObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "PolicyCore: not bound");
        return -1;
    }
    return sc_nargs(name, nargs, want);
}

/* pose_cov_update(P6, coil, current, var_amp, rel_model, current_sigma) -> bool */
static PyObject *Policy_pose_cov_update(PolicyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    long coil;
    double cur, var, rel, cs;
    int ok;
    if (po_ready(self, "pose_cov_update", nargs, 6) < 0 || sc_int(args[1], 0, self->n - 1, &coil, "coil") < 0 ||
        sc_double(args[2], &cur) < 0 || sc_double(args[3], &var) < 0 || sc_double(args[4], &rel) < 0 ||
        sc_double(args[5], &cs) < 0)
        return NULL;
    if (sc_doubles(args[0], 36, 1, &pv, "P6") < 0)
        return NULL;
    ok = ct_scp_pose_cov_update(&self->w, (double *)pv.buf, self->H + 18 * coil, self->h + 3 * coil, cur, var, rel,
                                cs);
    PyBuffer_Release(&pv);
    return PyBool_FromLong(ok);
}

/* range_limits(pp, P6, quiet, have_quiet, saturation_sigmas, range_t, margin, earth_max_t) */
static PyObject *Policy_range_limits(PolicyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double pp[3], quiet[3], P6[36], ss, rt, mg, em;
    int hq;
    if (po_ready(self, "range_limits", nargs, 8) < 0 || sc_copy_doubles(args[0], 3, pp, "pp") < 0 ||
        sc_copy_doubles(args[1], 36, P6, "P6") < 0 || sc_copy_doubles(args[2], 3, quiet, "quiet") < 0 ||
        (hq = PyObject_IsTrue(args[3])) < 0 || sc_double(args[4], &ss) < 0 || sc_double(args[5], &rt) < 0 ||
        sc_double(args[6], &mg) < 0 || sc_double(args[7], &em) < 0)
        return NULL;
    ct_scp_range_limits(self->n, self->h, pp, P6, quiet, hq, ss, rt, mg, em, self->lim);
    Py_RETURN_NONE;
}

static PyMethodDef Policy_methods[] = {
    {"pose_cov_update", (PyCFunction)(void (*)(void))Policy_pose_cov_update, METH_FASTCALL,
     "pose_cov_update(P6, coil, current, var_amp, rel_model, current_sigma) -> bool: PoseCovUpdate.apply"},
    {"range_limits", (PyCFunction)(void (*)(void))Policy_range_limits, METH_FASTCALL,
     "range_limits(pp, P6, quiet, have_quiet, saturation_sigmas, range_t, margin, earth_max_t): one sensor's "
     "magnetometer-range limits into lim (AdaptiveActuation._decide_limits)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject PolicyType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.PolicyCore",
    .tp_basicsize = sizeof(PolicyObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "PolicyCore(n, h, H, lim): the adaptive policy's eq-4 update of a pulse in flight and its current "
              "limits, bound to the decision model's arrays (actuate.single_coil_policy)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Policy_init,
    .tp_dealloc = (destructor)Policy_dealloc,
    .tp_methods = Policy_methods,
};

/* ------------------------------------------------------------ BoundsCore */
/* one SensorOutlook's (pp, smax6, smin6), its reference's (avg, law, P) or None, the mean budget's
 * (own, factor, held) or None, and the configuration (CT_BND_N floats) */
enum { BD_PP, BD_MX, BD_MN, BD_AVG, BD_LAW, BD_P, BD_OWN, BD_FACTOR, BD_HELD, BD_N };
static const char *bd_names[BD_N] = {"pp", "smax6", "smin6", "avg", "law", "P", "own", "factor", "held"};
static const Py_ssize_t bd_len[BD_N] = {3, 6, 6, 6, 2, CT_SC_CORE * CT_SC_CORE, 2, 2, 6};

typedef struct {
    PyObject_HEAD
    struct ct_scp_bounds b;
    Py_buffer views[BD_N];
    int nviews;
} BoundsObject;

static void Bounds_release(BoundsObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void Bounds_dealloc(BoundsObject *self)
{
    Bounds_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* BoundsCore(view, ref, mean, params): view = (pp, smax6, smin6), ref = (avg, law, P) or None,
 * mean = (own, factor, held) or None, params: CT_BND_N floats */
static int Bounds_init(BoundsObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"view", "ref", "mean", "params", NULL};
    PyObject *view, *ref, *mean, *params, *groups[3];
    double *ptr[BD_N];
    int g, i, k = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!OOO", kwlist, &PyTuple_Type, &view, &ref, &mean, &params))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "BoundsCore: already bound");
        return -1;
    }
    groups[0] = view;
    groups[1] = ref;
    groups[2] = mean;
    if (mean != Py_None && ref == Py_None) {
        PyErr_SetString(PyExc_ValueError, "BoundsCore: a mean budget needs its reference");
        return -1;
    }
    for (g = 0; g < 3; ++g) {
        PyObject *t = groups[g];
        if (t == Py_None && g > 0) {
            for (i = 0; i < 3; ++i)
                ptr[3 * g + i] = NULL;
            continue;
        }
        if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) != 3) {
            PyErr_Format(PyExc_TypeError, "BoundsCore: %s needs 3 arrays", g == 0 ? "view" : g == 1 ? "ref" : "mean");
            Bounds_release(self);
            return -1;
        }
        for (i = 0; i < 3; ++i) {
            int j = 3 * g + i;
            if (sc_doubles(PyTuple_GET_ITEM(t, i), bd_len[j], j != BD_PP && j != BD_AVG && j != BD_LAW && j != BD_P &&
                           j != BD_OWN, &self->views[k], bd_names[j]) < 0) {
                Bounds_release(self);
                return -1;
            }
            ptr[j] = (double *)self->views[k].buf;
            self->nviews = ++k;
        }
    }
    if (sc_copy_doubles(params, CT_BND_N, self->b.c, "params") < 0) {
        Bounds_release(self);
        return -1;
    }
    self->b.pp = ptr[BD_PP];
    self->b.mx = ptr[BD_MX];
    self->b.mn = ptr[BD_MN];
    self->b.avg = ptr[BD_AVG];
    self->b.law = ptr[BD_LAW];
    self->b.P = ptr[BD_P];
    self->b.own = ptr[BD_OWN];
    self->b.factor = ptr[BD_FACTOR];
    self->b.held = ptr[BD_HELD];
    return 0;
}

/* bounds(ref_active, warming, excess) */
static PyObject *Bounds_bounds(BoundsObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int active, warming;
    double excess;
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "BoundsCore: not bound");
        return NULL;
    }
    if (sc_nargs("bounds", nargs, 3) < 0 || (active = PyObject_IsTrue(args[0])) < 0 ||
        (warming = PyObject_IsTrue(args[1])) < 0 || sc_double(args[2], &excess) < 0)
        return NULL;
    ct_scp_bounds(&self->b, active, warming, excess);
    Py_RETURN_NONE;
}

static PyMethodDef Bounds_methods[] = {
    {"bounds", (PyCFunction)(void (*)(void))Bounds_bounds, METH_FASTCALL,
     "bounds(ref_active, warming, excess): AdaptiveActuation._bounds into smax6, smin6"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject BoundsType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.BoundsCore",
    .tp_basicsize = sizeof(BoundsObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "BoundsCore(view, ref, mean, params): one sensor's decision bounds bound to its arrays "
              "(actuate.single_coil_policy)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Bounds_init,
    .tp_dealloc = (destructor)Bounds_dealloc,
    .tp_methods = Bounds_methods,
};

/* --------------------------------------------------------------- NisCore */
/* coil_choice.NisMonitor's ring, bounds and state (track.single_coil_nis.CompiledNisMonitor) */
enum { NM_BUF, NM_BOUND, NM_ST, NM_N };

typedef struct {
    PyObject_HEAD
    struct ct_nis m;
    Py_buffer views[NM_N];
    int nviews;
} NisObject;

static void Nis_dealloc(NisObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* NisCore(buf, bound, st, window, min_count, dof, min_mean, max_scale, excess_gate, alpha) */
static int Nis_init(NisObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"buf", "bound", "st", "window", "min_count", "dof", "min_mean", "max_scale",
                             "excess_gate", "alpha", NULL};
    static const char *names[NM_N] = {"buf", "bound", "st"};
    PyObject *o[NM_N];
    struct ct_nis *m = &self->m;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOiiddddd", kwlist, &o[0], &o[1], &o[2], &m->window,
                                     &m->min_count, &m->dof, &m->min_mean, &m->max_scale, &m->excess_gate,
                                     &m->alpha))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "NisCore: already bound");
        return -1;
    }
    if (m->window < 1 || m->min_count < 1 || m->min_count > m->window || !(m->dof > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "NisCore: need 1 <= min_count <= window and dof > 0");
        return -1;
    }
    for (i = 0; i < NM_N; ++i) {
        Py_ssize_t n = i == NM_BUF ? m->window : (i == NM_BOUND ? m->window + 1 : CT_NIS_NST);
        if (sc_doubles(o[i], n, i != NM_BOUND, &self->views[i], names[i]) < 0) {
            while (self->nviews > 0)
                PyBuffer_Release(&self->views[--self->nviews]);
            return -1;
        }
        self->nviews = i + 1;
    }
    m->buf = (double *)self->views[NM_BUF].buf;
    m->bound = (const double *)self->views[NM_BOUND].buf;
    m->st = (double *)self->views[NM_ST].buf;
    return 0;
}

static PyObject *Nis_call(NisObject *self, PyObject *const *args, Py_ssize_t nargs, const char *name,
                          void (*f)(struct ct_nis *, double))
{
    double x;
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "NisCore: not bound");
        return NULL;
    }
    if (sc_nargs(name, nargs, 1) < 0 || sc_double(args[0], &x) < 0)
        return NULL;
    f(&self->m, x);
    Py_RETURN_NONE;
}

static PyObject *Nis_add(NisObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    return Nis_call(self, args, nargs, "add", ct_nis_add);
}

static PyObject *Nis_add_used(NisObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    return Nis_call(self, args, nargs, "add_used", ct_nis_add_used);
}

static PyMethodDef Nis_methods[] = {
    {"add", (PyCFunction)(void (*)(void))Nis_add, METH_FASTCALL, "add(nis_nominal): NisMonitor.add (ct_nis_add)"},
    {"add_used", (PyCFunction)(void (*)(void))Nis_add_used, METH_FASTCALL,
     "add_used(nis_used): NisMonitor.add_used (ct_nis_add_used)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject NisType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.NisCore",
    .tp_basicsize = sizeof(NisObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "NisCore(buf, bound, st, window, min_count, dof, min_mean, max_scale, excess_gate, alpha): a NIS "
              "monitor's window test bound to its arrays (actuate.coil_choice.NisMonitor)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Nis_init,
    .tp_dealloc = (destructor)Nis_dealloc,
    .tp_methods = Nis_methods,
};

/* ------------------------------------------------------------ the pulses' command and duty */
/* pulse_cmd_frame(seq, src, coil, pulse_id, current_ma, start_us, duration_us) -> bytes or None: one
 * COIL_PULSE_CMD frame as encode_frame makes it (None: a value the wire format refuses) */
static PyObject *sc_pulse_cmd_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_PCMD_FRAME_MAX];
    int64_t f[7];
    uint64_t start;
    int k;
    (void)mod;
    if (sc_nargs("pulse_cmd_frame", nargs, 7) < 0)
        return NULL;
    if (!ct_py_int_only(args[0], &f[0]) || !ct_py_int_only(args[1], &f[1])) {
        PyErr_SetString(PyExc_TypeError, "pulse_cmd_frame: seq and src must be integers");
        return NULL;
    }
    for (k = 2; k < 7; ++k)
        if (k != 5 && !ct_py_int_only(args[k], &f[k]))
            Py_RETURN_NONE;
    if (!ct_py_pack_Q(args[5], &start))                  /* start_us: 'Q' */
        Py_RETURN_NONE;
    k = ct_pulse_cmd_frame(out, (int)(f[0] & 0xFF), (int)(f[1] & 0xFF), f[2], f[3], f[4], start, f[6]);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* one PulseBook's duty history (n_coils x n_hist x 2 int64) bound, with the duty window and bound */
typedef struct {
    PyObject_HEAD
    Py_buffer view;
    int bound_view, n_coils, n_hist;
    int64_t window_us;
    double bound;
} DutyObject;

static void Duty_dealloc(DutyObject *self)
{
    if (self->bound_view)
        PyBuffer_Release(&self->view);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* DutyCore(hist, n_coils, n_hist, window_us, bound) */
static int Duty_init(DutyObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"hist", "n_coils", "n_hist", "window_us", "bound", NULL};
    PyObject *h;
    int nc, nh;
    long long w;
    double b;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OiiLd", kwlist, &h, &nc, &nh, &w, &b))
        return -1;
    if (self->bound_view) {
        PyErr_SetString(PyExc_RuntimeError, "DutyCore: already bound");
        return -1;
    }
    if (nc < 1 || nc > 64 || nh < 1 || nh > 4096) {
        PyErr_SetString(PyExc_ValueError, "DutyCore: n_coils in 1..64, n_hist in 1..4096");
        return -1;
    }
    if (sc_get(h, (Py_ssize_t)2 * nc * nh, 'q', 8, 0, &self->view, "hist") < 0)
        return -1;
    self->bound_view = 1;
    self->n_coils = nc;
    self->n_hist = nh;
    self->window_us = (int64_t)w;
    self->bound = b;
    return 0;
}

/* ok(c, start, length) -> bool: PulseBook.duty_ok (ct_scp_duty_ok) */
static PyObject *Duty_ok(DutyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long c;
    int64_t start, length;
    if (!self->bound_view) {
        PyErr_SetString(PyExc_RuntimeError, "DutyCore: not bound");
        return NULL;
    }
    if (sc_nargs("ok", nargs, 3) < 0 || sc_int(args[0], 0, self->n_coils - 1, &c, "coil") < 0)
        return NULL;
    if (!ct_py_int_only(args[1], &start) || !ct_py_int_only(args[2], &length)) {
        PyErr_SetString(PyExc_TypeError, "ok: start and length must be 64-bit integers");
        return NULL;
    }
    return PyBool_FromLong(ct_scp_duty_ok((const int64_t *)self->view.buf + (Py_ssize_t)2 * self->n_hist * c,
                                          self->n_hist, start, length, self->window_us, self->bound));
}

static PyMethodDef Duty_methods[] = {
    {"ok", (PyCFunction)(void (*)(void))Duty_ok, METH_FASTCALL,
     "ok(c, start, length) -> bool: PulseBook.duty_ok (ct_scp_duty_ok)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject DutyType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.DutyCore",
    .tp_basicsize = sizeof(DutyObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "DutyCore(hist, n_coils, n_hist, window_us, bound): PulseBook.duty_ok bound to the book's history "
              "(actuate.single_coil_pulses)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Duty_init,
    .tp_dealloc = (destructor)Duty_dealloc,
    .tp_methods = Duty_methods,
};

/* ------------------------------------------------------------ WhenCore */
/* one ActuationPolicy's var_max (6) and its outputs st (2: reason, worst) bound, with trace and the
 * interval */
typedef struct {
    PyObject_HEAD
    Py_buffer views[2];
    int nviews, trace;
    int64_t max_interval_us;
} WhenObject;

static void When_release(WhenObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
}

static void When_dealloc(WhenObject *self)
{
    When_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* WhenCore(var_max, st, trace, max_interval_us) */
static int When_init(WhenObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"var_max", "st", "trace", "max_interval_us", NULL};
    PyObject *vm, *st;
    int trace;
    long long mi;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOpL", kwlist, &vm, &st, &trace, &mi))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "WhenCore: already bound");
        return -1;
    }
    if (sc_doubles(vm, 6, 1, &self->views[0], "var_max") < 0)
        return -1;
    self->nviews = 1;
    if (sc_doubles(st, 2, 1, &self->views[1], "st") < 0) {
        When_release(self);
        return -1;
    }
    self->nviews = 2;
    self->trace = trace;
    self->max_interval_us = (int64_t)mi;
    return 0;
}

static int wh_ready(WhenObject *self, const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    if (!self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "WhenCore: not bound");
        return -1;
    }
    return sc_nargs(name, nargs, want);
}

/* set_bounds(sigma_max6) */
static PyObject *When_set_bounds(WhenObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double sm[6];
    if (wh_ready(self, "set_bounds", nargs, 1) < 0 || sc_copy_doubles(args[0], 6, sm, "sigma_max6") < 0)
        return NULL;
    ct_scp_policy_set_bounds((double *)self->views[0].buf, sm);
    Py_RETURN_NONE;
}

/* worst(P6): the value into st[1], and returned (a float) */
static PyObject *When_worst(WhenObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    double w;
    if (wh_ready(self, "worst", nargs, 1) < 0 || sc_doubles(args[0], 36, 0, &pv, "P6") < 0)
        return NULL;
    w = ct_scp_policy_worst((const double *)self->views[0].buf, (const double *)pv.buf, self->trace);
    ((double *)self->views[1].buf)[1] = w;
    PyBuffer_Release(&pv);
    return PyFloat_FromDouble(w);
}

/* due(P6, now_us, last_update_us) -> bool; the reason into st[0] */
static PyObject *When_due(WhenObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    int64_t now, last;
    int reason = 0, due;
    if (wh_ready(self, "due", nargs, 3) < 0)
        return NULL;
    if (!ct_py_int_only(args[1], &now) || !ct_py_int_only(args[2], &last)) {
        PyErr_SetString(PyExc_TypeError, "due: now_us and last_update_us must be 64-bit integers");
        return NULL;
    }
    if (sc_doubles(args[0], 36, 0, &pv, "P6") < 0)
        return NULL;
    due = ct_scp_policy_due((const double *)self->views[0].buf, (const double *)pv.buf, self->trace, now, last,
                            self->max_interval_us, &reason);
    PyBuffer_Release(&pv);
    ((double *)self->views[1].buf)[0] = (double)reason;
    return PyBool_FromLong(due);
}

static PyMethodDef When_methods[] = {
    {"set_bounds", (PyCFunction)(void (*)(void))When_set_bounds, METH_FASTCALL,
     "set_bounds(sigma_max6): ActuationPolicy.set_bounds (ct_scp_policy_set_bounds)"},
    {"worst", (PyCFunction)(void (*)(void))When_worst, METH_FASTCALL,
     "worst(P6) -> float: ActuationPolicy.worst, also into st[1] (ct_scp_policy_worst)"},
    {"due", (PyCFunction)(void (*)(void))When_due, METH_FASTCALL,
     "due(P6, now_us, last_update_us) -> bool: ActuationPolicy.due, the reason into st[0] (ct_scp_policy_due)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject WhenType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.WhenCore",
    .tp_basicsize = sizeof(WhenObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "WhenCore(var_max, st, trace, max_interval_us): coil_choice.ActuationPolicy's bounds, due test and "
              "worst ratio bound to its arrays (actuate.single_coil_policy.CompiledActuationPolicy)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)When_init,
    .tp_dealloc = (destructor)When_dealloc,
    .tp_methods = When_methods,
};

/* ------------------------------------------------------------ ViewCore */
/* one SensorOutlook's prediction in one call: its filter's SchepersCore, its BoundsCore and the
 * policy's WhenCore (references held), its P6 (6 x 6), pp (3, the bounds' own) and Rd (3 x 3) */
typedef struct {
    PyObject_HEAD
    PyObject *sc, *bd, *wh;
    Py_buffer views[3];
    int nviews;
} ViewObject;

static void View_release(ViewObject *self)
{
    while (self->nviews > 0)
        PyBuffer_Release(&self->views[--self->nviews]);
    Py_CLEAR(self->sc);
    Py_CLEAR(self->bd);
    Py_CLEAR(self->wh);
}

static void View_dealloc(ViewObject *self)
{
    View_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* ViewCore(ekf_core, bounds_core, when_core, P6, pp, Rd) */
static int View_init(ViewObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"ekf_core", "bounds_core", "when_core", "P6", "pp", "Rd", NULL};
    PyObject *sc, *bd, *wh, *P6, *pp, *Rd;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!O!O!OOO", kwlist, &SchepersCoreType, &sc, &BoundsType, &bd,
                                     &WhenType, &wh, &P6, &pp, &Rd))
        return -1;
    if (self->nviews || self->sc != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ViewCore: already bound");
        return -1;
    }
    if (!((SchepersCoreObject *)sc)->nviews || !((BoundsObject *)bd)->nviews || !((WhenObject *)wh)->nviews) {
        PyErr_SetString(PyExc_ValueError, "ViewCore: the cores must be bound");
        return -1;
    }
    if (sc_doubles(P6, 36, 1, &self->views[0], "P6") < 0)
        return -1;
    self->nviews = 1;
    if (sc_doubles(pp, 3, 1, &self->views[1], "pp") < 0 || (self->nviews = 2,
        sc_doubles(Rd, 9, 1, &self->views[2], "Rd") < 0)) {
        View_release(self);
        return -1;
    }
    self->nviews = 3;
    if ((const double *)self->views[1].buf != ((BoundsObject *)bd)->b.pp) {
        View_release(self);
        PyErr_SetString(PyExc_ValueError, "ViewCore: pp must be the bounds core's");
        return -1;
    }
    Py_INCREF(sc);
    Py_INCREF(bd);
    Py_INCREF(wh);
    self->sc = sc;
    self->bd = bd;
    self->wh = wh;
    return 0;
}

/* predict(horizon_us, ref_active, warming, excess): AdaptiveActuation._predict_view (the filter's
 * orientation into Rd, SchepersEKF.predict_pose over max(horizon_us, 0) in 8 steps, _bounds,
 * ActuationPolicy.set_bounds) */
static PyObject *View_predict(ViewObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    SchepersCoreObject *sc;
    int64_t h;
    int active, warming;
    double excess;
    if (self->sc == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ViewCore: not bound");
        return NULL;
    }
    if (sc_nargs("predict", nargs, 4) < 0)
        return NULL;
    if (!ct_py_int_only(args[0], &h)) {
        PyErr_SetString(PyExc_TypeError, "predict: horizon_us must be a 64-bit integer");
        return NULL;
    }
    if ((active = PyObject_IsTrue(args[1])) < 0 || (warming = PyObject_IsTrue(args[2])) < 0 ||
        sc_double(args[3], &excess) < 0)
        return NULL;
    sc = (SchepersCoreObject *)self->sc;
    memcpy(self->views[2].buf, sc->s.R, 9 * sizeof(double));
    ct_sc_predict_pose(&sc->s, (double)(h > 0 ? h : 0) * 1e-6, 8, (double *)self->views[0].buf,
                       (double *)self->views[1].buf);
    ct_scp_bounds(&((BoundsObject *)self->bd)->b, active, warming, excess);
    ct_scp_policy_set_bounds((double *)((WhenObject *)self->wh)->views[0].buf, ((BoundsObject *)self->bd)->b.mx);
    Py_RETURN_NONE;
}

static PyMethodDef View_methods[] = {
    {"predict", (PyCFunction)(void (*)(void))View_predict, METH_FASTCALL,
     "predict(horizon_us, ref_active, warming, excess): AdaptiveActuation._predict_view in one call"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ViewType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ViewCore",
    .tp_basicsize = sizeof(ViewObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ViewCore(ekf_core, bounds_core, when_core, P6, pp, Rd): one sensor's predicted pose covariance, "
              "bounds and the policy's bounds in one call (actuate.single_coil_policy)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)View_init,
    .tp_dealloc = (destructor)View_dealloc,
    .tp_methods = View_methods,
};

static PyMethodDef sc_functions[] = {
    {"pulse_cmd_frame", (PyCFunction)(void (*)(void))sc_pulse_cmd_frame, METH_FASTCALL,
     "pulse_cmd_frame(seq, src, coil, pulse_id, current_ma, start_us, duration_us) -> bytes or None: one "
     "COIL_PULSE_CMD frame as encode_frame makes it (ct_pulse_cmd_frame)"},
    {NULL, NULL, 0, NULL}};

/* ------------------------------------------------------------------ module */
int ct_register_single_coil(PyObject *m)
{
    if (PyType_Ready(&SchepersCoreType) < 0 || PyType_Ready(&SCUpdateType) < 0)
        return -1;
    Py_INCREF(&SchepersCoreType);
    if (PyModule_AddObject(m, "SchepersCore", (PyObject *)&SchepersCoreType) < 0) {
        Py_DECREF(&SchepersCoreType);
        return -1;
    }
    Py_INCREF(&SCUpdateType);
    if (PyModule_AddObject(m, "SingleCoilUpdateCore", (PyObject *)&SCUpdateType) < 0) {
        Py_DECREF(&SCUpdateType);
        return -1;
    }
    if (PyType_Ready(&FixedRefType) < 0 || PyType_Ready(&PolicyType) < 0 || PyType_Ready(&BoundsType) < 0)
        return -1;
    Py_INCREF(&BoundsType);
    if (PyModule_AddObject(m, "BoundsCore", (PyObject *)&BoundsType) < 0) {
        Py_DECREF(&BoundsType);
        return -1;
    }
    Py_INCREF(&FixedRefType);
    if (PyModule_AddObject(m, "FixedRefCore", (PyObject *)&FixedRefType) < 0) {
        Py_DECREF(&FixedRefType);
        return -1;
    }
    Py_INCREF(&PolicyType);
    if (PyModule_AddObject(m, "PolicyCore", (PyObject *)&PolicyType) < 0) {
        Py_DECREF(&PolicyType);
        return -1;
    }
    if (PyType_Ready(&NisType) < 0)
        return -1;
    Py_INCREF(&NisType);
    if (PyModule_AddObject(m, "NisCore", (PyObject *)&NisType) < 0) {
        Py_DECREF(&NisType);
        return -1;
    }
    if (PyType_Ready(&DutyType) < 0 || PyType_Ready(&WhenType) < 0 || PyType_Ready(&ViewType) < 0)
        return -1;
    Py_INCREF(&ViewType);
    if (PyModule_AddObject(m, "ViewCore", (PyObject *)&ViewType) < 0) {
        Py_DECREF(&ViewType);
        return -1;
    }
    Py_INCREF(&WhenType);
    if (PyModule_AddObject(m, "WhenCore", (PyObject *)&WhenType) < 0) {
        Py_DECREF(&WhenType);
        return -1;
    }
    Py_INCREF(&DutyType);
    if (PyModule_AddObject(m, "DutyCore", (PyObject *)&DutyType) < 0) {
        Py_DECREF(&DutyType);
        return -1;
    }
    if (PyModule_AddFunctions(m, sc_functions) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "PCMD_ID", CT_PCMD_ID) < 0 || PyModule_AddIntConstant(m, "PCMD_PAYLOAD", CT_PCMD_PAYLOAD) < 0 ||
        PyModule_AddIntConstant(m, "PCMD_CRC_EXTRA", CT_PCMD_CRC_EXTRA) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "NIS_NST", CT_NIS_NST) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "REF_NST", CT_REF_NST) < 0 || PyModule_AddIntConstant(m, "BND_N", CT_BND_N) < 0 ||
        PyModule_AddIntConstant(m, "SC_NST", CT_SCU_NST) < 0 ||
        PyModule_AddIntConstant(m, "SC_NIS_NOMINAL", CT_SCU_NIS_NOMINAL) < 0 ||
        PyModule_AddIntConstant(m, "SC_RS_N", SU_RS_N) < 0)
        return -1;
    return 0;
}

/* ------------------------------------------------- for py_sc_close.c (py_sc_close.h) */
struct ct_sc *ct_py_sc_state(PyObject *o)
{
    if (!PyObject_TypeCheck(o, &SchepersCoreType) || !((SchepersCoreObject *)o)->nviews)
        return NULL;
    return &((SchepersCoreObject *)o)->s;
}

int ct_py_scu_ready(PyObject *o, int nx)
{
    SCUpdateObject *u = (SCUpdateObject *)o;
    return PyObject_TypeCheck(o, &SCUpdateType) && u->nviews && u->nrviews && u->u.nx == nx;
}

int ct_py_scu_run(PyObject *o, double *P, const double *p, const double *R, long cp, long co, long coil,
                  const double *y, const double *var, double current, double rel_model, double r_scale, double gate,
                  long iters, long long count, struct ct_py_scu_out *out)
{
    SCUpdateObject *u = (SCUpdateObject *)o;
    struct ct_scm m;
    int flags;
    m.current = current;
    m.rel_model = rel_model;
    m.r_scale = r_scale;
    m.gain = -1;
    m.gain_current = 0.0;
    flags = su_run(u, P, p, R, cp, co, coil, y, var, &m, gate, iters, count);
    out->applied = (int64_t)u->rs[SU_RS_APPLIED];
    out->rejected = (int64_t)u->rs[SU_RS_REJECTED];
    out->nis = u->rs[SU_RS_NIS];
    out->nis_last = u->rs[SU_RS_NIS_LAST];
    out->evals = u->rs[SU_RS_EVALS];
    out->nis_nominal = u->u.st[CT_SCU_NIS_NOMINAL];
    out->dx = u->u.dx;
    return flags;
}

int ct_py_scu_coils(PyObject *o)
{
    return ((SCUpdateObject *)o)->ncoils;
}
