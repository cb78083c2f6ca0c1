/*
 * CPython glue of the solve's finish and the POSE's quality (src/finish.c): the types SolveFinish,
 * BurstQuality and ReportPose, bound once (start-up) to the caller's numpy arrays; their per-call methods
 * (METH_FASTCALL) take numbers and the call's input arrays, write into the bound buffers and
 * create no Python object (the small ints they return are the interpreter's cached ones).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* a C-contiguous buffer of at least n items of `size` bytes whose format is one of `fmts`, or -1
 * with TypeError naming `what` (or, quiet, -1 with no error set) */
/* ct_py_buffer (py_glue.h), and exactly n items when n > 0; quiet: no exception set on refusal (the
 * caller falls back to the Python) */
static int fin_buffer(PyObject *obj, Py_ssize_t n, Py_ssize_t size, const char *fmts, int writable, Py_buffer *v,
                      const char *what, int quiet)
{
    if (ct_py_buffer(obj, n, size, fmts, writable, v, what) < 0) {
        if (quiet)
            PyErr_Clear();
        return -1;
    }
    if (n > 0 && v->len != n * size) {
        PyBuffer_Release(v);
        if (!quiet)
            PyErr_Format(PyExc_TypeError, "%s: needs %zd items of %zd bytes (format %s)", what, n, size, fmts);
        return -1;
    }
    return 0;
}

static int fin_double(PyObject *o, double *x)
{
    return ct_py_double(o, x);
}

static int fin_int64(PyObject *o, int64_t *x)
{
    return ct_py_int64(o, x);
}

/* ------------------------------------------------------------ SolveFinish */
#define SF_NBUF 4
typedef struct {
    PyObject_HEAD
    struct ct_warmcheck w;
    double *par;                 /* check_hemi, hx, hy, hz: written by the solver's begin */
    double *p, *cov, *work;
    double tol;                  /* linalg.ORTHONORMAL_TOL, for nearest */
    Py_buffer views[SF_NBUF];
    int bound;
} SolveFinishObject;

static void SolveFinish_dealloc(SolveFinishObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < SF_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int SolveFinish_init(SolveFinishObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "gate", "cx", "cy", "cz", "par", "p", "cov", "work", "tol", NULL};
    static const char *names[SF_NBUF] = {"par", "p", "cov", "work"};
    const Py_ssize_t len[SF_NBUF] = {4, 3, 36, CT_ROBUST6_WORK};
    PyObject *o[SF_NBUF];
    double gate, cx, cy, cz, tol = 1e-12;
    int n, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iddddOOOO|d", kwlist, &n, &gate, &cx, &cy, &cz, &o[0], &o[1], &o[2],
                                     &o[3], &tol))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "SolveFinish: already bound");
        return -1;
    }
    for (i = 0; i < SF_NBUF; ++i)
        if (fin_buffer(o[i], len[i], 8, "d", 1, &self->views[i], names[i], 0) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
    self->par = (double *)self->views[0].buf;
    self->p = (double *)self->views[1].buf;
    self->cov = (double *)self->views[2].buf;
    self->work = (double *)self->views[3].buf;
    self->tol = tol;
    self->w.n = n;
    self->w.gate = gate;
    self->w.cbar[0] = cx;
    self->w.cbar[1] = cy;
    self->w.cbar[2] = cz;
    self->bound = 1;
    return 0;
}

/* finish(A, check, state, cost) -> -1, 0 or 1 (ct_solve_finish) */
static PyObject *SolveFinish_finish(SolveFinishObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer va;
    long check, state;
    double cost;
    int r;
    if (!self->bound || nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "SolveFinish.finish(A, check, state, cost): bound, four arguments");
        return NULL;
    }
    check = PyObject_IsTrue(args[1]);
    state = PyLong_AsLong(args[2]);
    if (check < 0 || (state == -1 && PyErr_Occurred()) || fin_double(args[3], &cost) < 0)
        return NULL;
    if (fin_buffer(args[0], 36, 8, "d", 0, &va, "A", 0) < 0)
        return NULL;
    self->w.check_hemi = self->par[0] != 0.0;
    self->w.hemi[0] = self->par[1];
    self->w.hemi[1] = self->par[2];
    self->w.hemi[2] = self->par[3];
    r = ct_solve_finish(&self->w, (int)check, (int)state, cost, self->p, (const double *)va.buf, self->cov,
                        self->work);
    PyBuffer_Release(&va);
    return PyLong_FromLong(r);
}

/* inverse(A) -> None: RobustInverse6.into and RotationMargin.into of A into the bound cov */
static PyObject *SolveFinish_inverse(SolveFinishObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer va;
    if (!self->bound || nargs != 1) {
        PyErr_SetString(PyExc_TypeError, "SolveFinish.inverse(A): bound, one argument");
        return NULL;
    }
    if (fin_buffer(args[0], 36, 8, "d", 0, &va, "A", 0) < 0)
        return NULL;
    ct_robust_inverse6((const double *)va.buf, self->cov, self->work);
    PyBuffer_Release(&va);
    Py_RETURN_NONE;
}

/* nearest(m, out) -> True, or None for arrays of another kind: linalg.nearest_rotation of m (9)
 * into out (9, writable) with the bound work (ct_nearest_rotation) */
static PyObject *SolveFinish_nearest(SolveFinishObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vm, vo;
    if (!self->bound || nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "SolveFinish.nearest(m, out): bound, two arguments");
        return NULL;
    }
    if (fin_buffer(args[0], 9, 8, "d", 0, &vm, "m", 1) < 0)
        Py_RETURN_NONE;
    if (fin_buffer(args[1], 9, 8, "d", 1, &vo, "out", 1) < 0) {
        PyBuffer_Release(&vm);
        Py_RETURN_NONE;
    }
    ct_nearest_rotation((const double *)vm.buf, (double *)vo.buf, self->work, self->tol);
    PyBuffer_Release(&vm);
    PyBuffer_Release(&vo);
    Py_RETURN_TRUE;
}

static PyMethodDef SolveFinish_methods[] = {
    {"nearest", (PyCFunction)(void (*)(void))SolveFinish_nearest, METH_FASTCALL,
     "nearest(m, out) -> True (linalg.nearest_rotation of m into out) or None (an array of another kind)"},
    {"finish", (PyCFunction)(void (*)(void))SolveFinish_finish, METH_FASTCALL,
     "finish(A, check, state, cost) -> -1 (check and the warm start failed), 0 or 1 (the covariance of A "
     "written; 1: p and cov[0] finite)"},
    {"inverse", (PyCFunction)(void (*)(void))SolveFinish_inverse, METH_FASTCALL,
     "inverse(A): RobustInverse6.into(A, cov) alone"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SolveFinishType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.SolveFinish",
    .tp_basicsize = sizeof(SolveFinishObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SolveFinish(n, gate, cx, cy, cz, par, p, cov, work): a pose solver's finish (warm-start checks, "
              "robust covariance with its rotation margin) bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)SolveFinish_init,
    .tp_dealloc = (destructor)SolveFinish_dealloc,
    .tp_methods = SolveFinish_methods,
};

/* ----------------------------------------------------------- BurstQuality */
#define BQ_NBUF 9
typedef struct {
    PyObject_HEAD
    struct ct_quality q;
    double *prev, *motion;
    Py_ssize_t rows;
    Py_buffer views[BQ_NBUF];
    int bound;
} BurstQualityObject;

static void BurstQuality_dealloc(BurstQualityObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < BQ_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int BurstQuality_init(BurstQualityObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "dof", "scale", "max_gap_us", "centers", "prev", "H", "u", "g", "dx", "d", "xd",
                             "motion", NULL};
    static const char *names[BQ_NBUF] = {"centers", "prev", "H", "u", "g", "dx", "d", "xd", "motion"};
    PyObject *o[BQ_NBUF];
    Py_ssize_t len[BQ_NBUF];
    double *ptr[BQ_NBUF];
    double scale, gap;
    int n, dof, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiddOOOOOOOOO", kwlist, &n, &dof, &scale, &gap, &o[0], &o[1], &o[2],
                                     &o[3], &o[4], &o[5], &o[6], &o[7], &o[8]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "BurstQuality: already bound");
        return -1;
    }
    if (n < 1 || n > 4096) {
        PyErr_Format(PyExc_ValueError, "BurstQuality: n must be in 1..4096, got %d", n);
        return -1;
    }
    len[0] = 3 * n;
    len[2] = 18 * n;
    len[3] = 3 * n;
    len[4] = len[5] = len[7] = 6;
    len[6] = n;
    len[8] = 2;
    for (i = 0; i < BQ_NBUF; ++i) {
        int r;
        if (i == 1) {             /* prev: (rows, 14), any number of rows */
            r = fin_buffer(o[i], 0, 8, "d", 1, &self->views[i], names[i], 1);
            if (r == 0 && self->views[i].len % (14 * 8) != 0) {
                PyBuffer_Release(&self->views[i]);
                r = -1;
            }
            if (r < 0)
                PyErr_SetString(PyExc_TypeError, "prev: needs a writable C-contiguous float64 buffer of rows of 14");
        } else {
            r = fin_buffer(o[i], len[i], 8, "d", i != 0, &self->views[i], names[i], 0);
        }
        if (r < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        ptr[i] = (double *)self->views[i].buf;
    }
    self->rows = self->views[1].len / (14 * 8);
    self->q.n = n;
    self->q.dof = dof;
    self->q.scale = scale;
    self->q.max_gap_us = gap;
    self->q.centers = ptr[0];
    self->prev = ptr[1];
    self->q.H = ptr[2];
    self->q.u = ptr[3];
    self->q.g = ptr[4];
    self->q.dx = ptr[5];
    self->q.d = ptr[6];
    self->q.xd = ptr[7];
    self->motion = ptr[8];
    self->bound = 1;
    return 0;
}

/* grade(row, t_us, cost, nis, quiet, cov, p, R, S, sigma, start, end) -> quality or None (an
 * array of another kind: the caller grades in Python) */
static PyObject *BurstQuality_grade(BurstQualityObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *names[7] = {"cov", "p", "R", "S", "sigma", "start", "end"};
    Py_buffer v[7];
    Py_ssize_t len[7];
    int64_t row, t_us;
    double cost, nis, quiet;
    int i, k, q;
    if (!self->bound || nargs != 12) {
        PyErr_SetString(PyExc_TypeError, "BurstQuality.grade(row, t_us, cost, nis, quiet, cov, p, R, S, sigma, start, "
                                         "end): bound, twelve arguments");
        return NULL;
    }
    if (fin_int64(args[0], &row) < 0 || fin_int64(args[1], &t_us) < 0 || fin_double(args[2], &cost) < 0 ||
        fin_double(args[3], &nis) < 0 || fin_double(args[4], &quiet) < 0)
        return NULL;
    if (row >= self->rows) {
        PyErr_SetString(PyExc_IndexError, "BurstQuality.grade: row beyond prev");
        return NULL;
    }
    len[0] = 36;
    len[1] = 3;
    len[2] = 9;
    len[3] = len[4] = 3 * self->q.n;
    len[5] = len[6] = self->q.n;
    for (i = 0; i < 7; ++i)
        if (fin_buffer(args[5 + i], len[i], 8, i < 5 ? "d" : "ql", 0, &v[i], names[i], 1) < 0) {
            for (k = 0; k < i; ++k)
                PyBuffer_Release(&v[k]);
            Py_RETURN_NONE;
        }
    q = ct_grade_burst(&self->q, row < 0 ? NULL : self->prev + 14 * row, t_us, cost, (const double *)v[0].buf,
                       (const double *)v[1].buf, (const double *)v[2].buf, (const double *)v[3].buf,
                       (const double *)v[4].buf, (const int64_t *)v[5].buf, (const int64_t *)v[6].buf, nis, quiet,
                       self->motion);
    for (i = 0; i < 7; ++i)
        PyBuffer_Release(&v[i]);
    return PyLong_FromLong(q);
}

static PyMethodDef BurstQuality_methods[] = {
    {"grade", (PyCFunction)(void (*)(void))BurstQuality_grade, METH_FASTCALL,
     "grade(row, t_us, cost, nis, quiet, cov, p, R, S, sigma, start, end) -> quality (PoseQuality.grade_burst; "
     "motion_m2, chi2_motion into motion) or None for arrays of another kind"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject BurstQualityType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.BurstQuality",
    .tp_basicsize = sizeof(BurstQualityObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "BurstQuality(n, dof, scale, max_gap_us, centers, prev, H, u, g, dx, d, xd, motion): the quality "
              "of a burst's pose (PoseQuality.grade_burst) bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)BurstQuality_init,
    .tp_dealloc = (destructor)BurstQuality_dealloc,
    .tp_methods = BurstQuality_methods,
};

/* ------------------------------------------------------------- ReportPose */
#define RP_NBUF 3
typedef struct {
    PyObject_HEAD
    double *p, *R, *q;
    Py_buffer views[RP_NBUF];
    int bound;
} ReportPoseObject;

static void ReportPose_dealloc(ReportPoseObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < RP_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ReportPose_init(ReportPoseObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"position", "rotation", "q", NULL};
    static const char *names[RP_NBUF] = {"position", "rotation", "q"};
    const Py_ssize_t len[RP_NBUF] = {3, 9, 4};
    PyObject *o[RP_NBUF];
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOO", kwlist, &o[0], &o[1], &o[2]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ReportPose: already bound");
        return -1;
    }
    for (i = 0; i < RP_NBUF; ++i)
        if (fin_buffer(o[i], len[i], 8, "d", i == 2, &self->views[i], names[i], 0) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
    self->p = (double *)self->views[0].buf;
    self->R = (double *)self->views[1].buf;
    self->q = (double *)self->views[2].buf;
    self->bound = 1;
    return 0;
}

/* take(dst_p, dst_R, range_m) -> True, False or None (ct_report_take; None: arrays of another kind) */
static PyObject *ReportPose_take(ReportPoseObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vp, vr;
    double range_m;
    int r;
    if (!self->bound || nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "ReportPose.take(dst_p, dst_R, range_m): bound, three arguments");
        return NULL;
    }
    if (fin_double(args[2], &range_m) < 0)
        return NULL;
    if (fin_buffer(args[0], 3, 8, "d", 1, &vp, "dst_p", 1) < 0)
        Py_RETURN_NONE;
    if (fin_buffer(args[1], 9, 8, "d", 1, &vr, "dst_R", 1) < 0) {
        PyBuffer_Release(&vp);
        Py_RETURN_NONE;
    }
    r = ct_report_take(self->p, self->R, range_m, (double *)vp.buf, (double *)vr.buf);
    PyBuffer_Release(&vp);
    PyBuffer_Release(&vr);
    return PyBool_FromLong(r);
}

/* quat(R) -> True or None: rotation.quat_tuple of R (9) into the bound q (ct_quat_from_elements) */
static PyObject *ReportPose_quat(ReportPoseObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vr;
    if (!self->bound || nargs != 1) {
        PyErr_SetString(PyExc_TypeError, "ReportPose.quat(R): bound, one argument");
        return NULL;
    }
    if (fin_buffer(args[0], 9, 8, "d", 0, &vr, "R", 1) < 0)
        Py_RETURN_NONE;
    ct_quat_from_elements((const double *)vr.buf, self->q);
    PyBuffer_Release(&vr);
    Py_RETURN_TRUE;
}

static PyMethodDef ReportPose_methods[] = {
    {"take", (PyCFunction)(void (*)(void))ReportPose_take, METH_FASTCALL,
     "take(dst_p, dst_R, range_m) -> True (in range: copied), False, or None (arrays of another kind)"},
    {"quat", (PyCFunction)(void (*)(void))ReportPose_quat, METH_FASTCALL,
     "quat(R) -> True (quat_tuple of R into q) or None (an array of another kind)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ReportPoseType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ReportPose",
    .tp_basicsize = sizeof(ReportPoseObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ReportPose(position, rotation, q): a tracker's report of its solver's pose (the range check, the "
              "copies, the quaternion) bound to the solver's results and a quaternion buffer",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ReportPose_init,
    .tp_dealloc = (destructor)ReportPose_dealloc,
    .tp_methods = ReportPose_methods,
};

/* quality_from(var_trace_m2, x, scale_m, motion_m2) -> int (track.quality.quality_from) */
static PyObject *fin_quality_from(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double a[4];
    int i;
    (void)mod;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "quality_from(var_trace_m2, x, scale_m, motion_m2)");
        return NULL;
    }
    for (i = 0; i < 4; ++i)
        if (fin_double(args[i], &a[i]) < 0)
            return NULL;
    return PyLong_FromLong(ct_quality_from(a[0], a[1], a[2], a[3]));
}

/* jacobi_eigh(a, n, w, v, sweeps) -> None (linalg.jacobi_eigh) */
static PyObject *fin_jacobi_eigh(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer va, vw, vv;
    long n, sweeps;
    (void)mod;
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "jacobi_eigh(a, n, w, v, sweeps)");
        return NULL;
    }
    n = PyLong_AsLong(args[1]);
    sweeps = PyLong_AsLong(args[4]);
    if (PyErr_Occurred())
        return NULL;
    if (n < 1 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "jacobi_eigh: n must be in 1..64");
        return NULL;
    }
    if (fin_buffer(args[0], n * n, 8, "d", 1, &va, "a", 0) < 0)
        return NULL;
    if (fin_buffer(args[2], n, 8, "d", 1, &vw, "w", 0) < 0) {
        PyBuffer_Release(&va);
        return NULL;
    }
    if (fin_buffer(args[3], n * n, 8, "d", 1, &vv, "v", 0) < 0) {
        PyBuffer_Release(&va);
        PyBuffer_Release(&vw);
        return NULL;
    }
    ct_fin_jacobi_eigh((double *)va.buf, (int)n, (double *)vw.buf, (double *)vv.buf, (int)sweeps);
    PyBuffer_Release(&va);
    PyBuffer_Release(&vw);
    PyBuffer_Release(&vv);
    Py_RETURN_NONE;
}

/* rotation_margin(cov) -> None (pose.covariance.RotationMargin.into) */
static PyObject *fin_rotation_margin(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vc;
    (void)mod;
    if (nargs != 1) {
        PyErr_SetString(PyExc_TypeError, "rotation_margin(cov)");
        return NULL;
    }
    if (fin_buffer(args[0], 36, 8, "d", 1, &vc, "cov", 0) < 0)
        return NULL;
    ct_rotation_margin((double *)vc.buf);
    PyBuffer_Release(&vc);
    Py_RETURN_NONE;
}

static PyMethodDef fin_functions[] = {
    {"finish_quality_from", (PyCFunction)(void (*)(void))fin_quality_from, METH_FASTCALL,
     "quality_from(var_trace_m2, x, scale_m, motion_m2) -> int (track.quality.quality_from)"},
    {"finish_jacobi_eigh", (PyCFunction)(void (*)(void))fin_jacobi_eigh, METH_FASTCALL,
     "jacobi_eigh(a, n, w, v, sweeps): linalg.jacobi_eigh in place"},
    {"finish_rotation_margin", (PyCFunction)(void (*)(void))fin_rotation_margin, METH_FASTCALL,
     "rotation_margin(cov): pose.covariance.RotationMargin.into in place"},
    {NULL, NULL, 0, NULL}};

int ct_register_finish(PyObject *m)
{
    PyMethodDef *f;
    if (PyType_Ready(&SolveFinishType) < 0 || PyType_Ready(&BurstQualityType) < 0 ||
        PyType_Ready(&ReportPoseType) < 0)
        return -1;
    Py_INCREF(&SolveFinishType);
    if (PyModule_AddObject(m, "SolveFinish", (PyObject *)&SolveFinishType) < 0) {
        Py_DECREF(&SolveFinishType);
        return -1;
    }
    Py_INCREF(&BurstQualityType);
    if (PyModule_AddObject(m, "BurstQuality", (PyObject *)&BurstQualityType) < 0) {
        Py_DECREF(&BurstQualityType);
        return -1;
    }
    Py_INCREF(&ReportPoseType);
    if (PyModule_AddObject(m, "ReportPose", (PyObject *)&ReportPoseType) < 0) {
        Py_DECREF(&ReportPoseType);
        return -1;
    }
    if (PyModule_AddIntConstant(m, "FINISH_WORK", CT_ROBUST6_WORK) < 0)
        return -1;
    for (f = fin_functions; f->ml_name != NULL; ++f) {
        PyObject *fn = PyCFunction_NewEx(f, NULL, NULL);
        if (fn == NULL || PyModule_AddObject(m, f->ml_name, fn) < 0) {
            Py_XDECREF(fn);
            return -1;
        }
    }
    return 0;
}
