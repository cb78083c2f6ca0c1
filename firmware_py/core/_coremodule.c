/*
 * coiltrack.firmware._core: the thin CPython glue of the compiled core.
 *
 * Objects bind the caller's numpy arrays once (start-up) through the buffer
 * protocol and keep their pointers; the per-call methods use METH_FASTCALL,
 * read their float arguments in place and write into caller-owned buffers,
 * so a call creates no Python object (it returns None).  No numpy header is
 * needed to build it.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

#define CT_MAX_COILS 64


/* ------------------------------------------------------------------ buffers */
static int is_double_format(const Py_buffer *v)
{
    const char *f = ct_py_format(v);
    return v->itemsize == (Py_ssize_t)sizeof(double) && f[0] == 'd' && f[1] == '\0';
}

/* a C-contiguous float64 buffer of at least n doubles, or -1 with TypeError naming `what` */
static int get_doubles(PyObject *obj, Py_ssize_t n, int writable, Py_buffer *view, const char *what)
{
    return ct_py_buffer(obj, n, (Py_ssize_t)sizeof(double), "d", writable, view, what);
}

/* a 3x3 rotation (array, 2-D or flat memoryview, any strides) into r[9], row-major */
static int get_matrix3(PyObject *obj, double *r)
{
    Py_buffer v;
    int i, k;
    if (PyObject_GetBuffer(obj, &v, PyBUF_RECORDS_RO) < 0) {
        PyErr_SetString(PyExc_TypeError, "R: needs a float64 buffer of shape (3, 3) or (9,)");
        return -1;
    }
    if (!is_double_format(&v) || !((v.ndim == 2 && v.shape[0] == 3 && v.shape[1] == 3) ||
                                   (v.ndim == 1 && v.shape[0] == 9))) {
        PyBuffer_Release(&v);
        PyErr_SetString(PyExc_TypeError, "R: needs a float64 buffer of shape (3, 3) or (9,)");
        return -1;
    }
    if (v.ndim == 2) {
        for (i = 0; i < 3; ++i)
            for (k = 0; k < 3; ++k)
                memcpy(&r[3 * i + k], (const char *)v.buf + i * v.strides[0] + k * v.strides[1],
                       sizeof(double));
    } else {
        for (i = 0; i < 9; ++i)
            memcpy(&r[i], (const char *)v.buf + i * v.strides[0], sizeof(double));
    }
    PyBuffer_Release(&v);
    return 0;
}

/* n currents from a float64 buffer or a tuple / list of numbers into c[n] */
static int get_currents(PyObject *obj, int n, double *c)
{
    Py_ssize_t i;
    if (PyTuple_Check(obj) || PyList_Check(obj)) {
        if (PySequence_Fast_GET_SIZE(obj) < n) {
            PyErr_Format(PyExc_ValueError, "cur: needs %d currents", n);
            return -1;
        }
        for (i = 0; i < n; ++i) {
            c[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(obj, i));
            if (c[i] == -1.0 && PyErr_Occurred())
                return -1;
        }
        return 0;
    } else {
        Py_buffer v;
        if (get_doubles(obj, n, 0, &v, "cur") < 0)
            return -1;
        memcpy(c, v.buf, (size_t)n * sizeof(double));
        PyBuffer_Release(&v);
        return 0;
    }
}

static int get_double(PyObject *o, double *x)
{
    return ct_py_double(o, x);
}

static int check_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    return ct_py_nargs(name, nargs, want);
}

/* ------------------------------------------------------------------ Signal */
typedef struct {
    PyObject_HEAD
    int n;
    Py_buffer geom_view, b_view, j_view;
    int bound;
    const double *geom;
    double *B, *J;
} SignalObject;

static void Signal_dealloc(SignalObject *self)
{
    if (self->bound) {
        PyBuffer_Release(&self->geom_view);
        PyBuffer_Release(&self->b_view);
        PyBuffer_Release(&self->j_view);
    }
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Signal_init(SignalObject *self, PyObject *args, PyObject *kw)
{
    PyObject *geom, *B, *J;
    int n;
    static char *kwlist[] = {"geom", "n", "B", "J", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OiOO", kwlist, &geom, &n, &B, &J))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "Signal: already bound");
        return -1;
    }
    if (n < 1 || n > CT_MAX_COILS) {
        PyErr_Format(PyExc_ValueError, "Signal: n must be in 1..%d, got %d", CT_MAX_COILS, n);
        return -1;
    }
    if (get_doubles(geom, (Py_ssize_t)n * CT_COIL_STRIDE, 0, &self->geom_view, "geom") < 0)
        return -1;
    if (get_doubles(B, (Py_ssize_t)n * 3, 1, &self->b_view, "B") < 0) {
        PyBuffer_Release(&self->geom_view);
        return -1;
    }
    if (get_doubles(J, (Py_ssize_t)n * 9, 1, &self->j_view, "J") < 0) {
        PyBuffer_Release(&self->geom_view);
        PyBuffer_Release(&self->b_view);
        return -1;
    }
    self->n = n;
    self->geom = (const double *)self->geom_view.buf;
    self->B = (double *)self->b_view.buf;
    self->J = (double *)self->j_view.buf;
    self->bound = 1;
    return 0;
}

static int Signal_ready(SignalObject *self)
{
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "Signal: not bound");
        return -1;
    }
    return 0;
}

/* fields(px, py, pz, cur, jac) */
static PyObject *Signal_fields(SignalObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double px, py, pz, cur[CT_MAX_COILS];
    int jac;
    if (Signal_ready(self) < 0 || check_nargs("fields", nargs, 5) < 0)
        return NULL;
    if (get_double(args[0], &px) < 0 || get_double(args[1], &py) < 0 || get_double(args[2], &pz) < 0)
        return NULL;
    if (get_currents(args[3], self->n, cur) < 0)
        return NULL;
    jac = PyObject_IsTrue(args[4]);
    if (jac < 0)
        return NULL;
    ct_signal_fields(self->geom, self->n, px, py, pz, cur, jac, self->B, self->J);
    Py_RETURN_NONE;
}

/* project(R, h): h = R^T B after fields (B possibly corrected by the caller) */
static PyObject *Signal_project(SignalObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double R[9];
    Py_buffer hv;
    if (Signal_ready(self) < 0 || check_nargs("project", nargs, 2) < 0)
        return NULL;
    if (get_matrix3(args[0], R) < 0 || get_doubles(args[1], 3 * self->n, 1, &hv, "h") < 0)
        return NULL;
    ct_signal_project(self->n, R, self->B, (double *)hv.buf);
    PyBuffer_Release(&hv);
    Py_RETURN_NONE;
}

/* project_jac(R, h, H) */
static PyObject *Signal_project_jac(SignalObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double R[9];
    Py_buffer hv, Hv;
    if (Signal_ready(self) < 0 || check_nargs("project_jac", nargs, 3) < 0)
        return NULL;
    if (get_matrix3(args[0], R) < 0 || get_doubles(args[1], 3 * self->n, 1, &hv, "h") < 0)
        return NULL;
    if (get_doubles(args[2], 18 * self->n, 1, &Hv, "H") < 0) {
        PyBuffer_Release(&hv);
        return NULL;
    }
    ct_signal_project_jac(self->n, R, self->B, self->J, (double *)hv.buf, (double *)Hv.buf);
    PyBuffer_Release(&hv);
    PyBuffer_Release(&Hv);
    Py_RETURN_NONE;
}

/* predict(px, py, pz, R, cur, h): fields without the gradient, then h = R^T B */
static PyObject *Signal_predict(SignalObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double px, py, pz, R[9], cur[CT_MAX_COILS];
    Py_buffer hv;
    if (Signal_ready(self) < 0 || check_nargs("predict", nargs, 6) < 0)
        return NULL;
    if (get_double(args[0], &px) < 0 || get_double(args[1], &py) < 0 || get_double(args[2], &pz) < 0)
        return NULL;
    if (get_matrix3(args[3], R) < 0 || get_currents(args[4], self->n, cur) < 0)
        return NULL;
    if (get_doubles(args[5], 3 * self->n, 1, &hv, "h") < 0)
        return NULL;
    ct_signal_fields(self->geom, self->n, px, py, pz, cur, 0, self->B, self->J);
    ct_signal_project(self->n, R, self->B, (double *)hv.buf);
    PyBuffer_Release(&hv);
    Py_RETURN_NONE;
}

/* measure(px, py, pz, R, cur, h, H): fields and gradients, then h and H */
static PyObject *Signal_measure(SignalObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double px, py, pz, R[9], cur[CT_MAX_COILS];
    Py_buffer hv, Hv;
    if (Signal_ready(self) < 0 || check_nargs("measure", nargs, 7) < 0)
        return NULL;
    if (get_double(args[0], &px) < 0 || get_double(args[1], &py) < 0 || get_double(args[2], &pz) < 0)
        return NULL;
    if (get_matrix3(args[3], R) < 0 || get_currents(args[4], self->n, cur) < 0)
        return NULL;
    if (get_doubles(args[5], 3 * self->n, 1, &hv, "h") < 0)
        return NULL;
    if (get_doubles(args[6], 18 * self->n, 1, &Hv, "H") < 0) {
        PyBuffer_Release(&hv);
        return NULL;
    }
    ct_signal_fields(self->geom, self->n, px, py, pz, cur, 1, self->B, self->J);
    ct_signal_project_jac(self->n, R, self->B, self->J, (double *)hv.buf, (double *)Hv.buf);
    PyBuffer_Release(&hv);
    PyBuffer_Release(&Hv);
    Py_RETURN_NONE;
}

static PyMethodDef Signal_methods[] = {
    {"fields", (PyCFunction)(void (*)(void))Signal_fields, METH_FASTCALL,
     "fields(px, py, pz, cur, jac): every coil's B (and J) into the bound buffers"},
    {"predict", (PyCFunction)(void (*)(void))Signal_predict, METH_FASTCALL,
     "predict(px, py, pz, R, cur, h): signals h = R^T B_j"},
    {"measure", (PyCFunction)(void (*)(void))Signal_measure, METH_FASTCALL,
     "measure(px, py, pz, R, cur, h, H): signals and the pose Jacobian"},
    {"project", (PyCFunction)(void (*)(void))Signal_project, METH_FASTCALL,
     "project(R, h): h = R^T B from the bound B"},
    {"project_jac", (PyCFunction)(void (*)(void))Signal_project_jac, METH_FASTCALL,
     "project_jac(R, h, H): h and H from the bound B and J"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject SignalType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Signal",
    .tp_basicsize = sizeof(SignalObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Signal(geom, n, B, J): the signal model's kernels bound to caller-owned buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Signal_init,
    .tp_dealloc = (destructor)Signal_dealloc,
    .tp_methods = Signal_methods,
};

/* ------------------------------------------------------------- CovPredict */
typedef struct {
    PyObject_HEAD
    int n;
    Py_buffer a_view, q_view, t_view;
    int bound;
} CovPredictObject;

static void CovPredict_dealloc(CovPredictObject *self)
{
    if (self->bound) {
        PyBuffer_Release(&self->a_view);
        PyBuffer_Release(&self->q_view);
        PyBuffer_Release(&self->t_view);
    }
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int CovPredict_init(CovPredictObject *self, PyObject *args, PyObject *kw)
{
    PyObject *A, *Q, *T;
    int n;
    Py_ssize_t nn;
    static char *kwlist[] = {"n", "A", "Q", "T", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOO", kwlist, &n, &A, &Q, &T))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "CovPredict: already bound");
        return -1;
    }
    if (n < 1 || n > 256) {
        PyErr_Format(PyExc_ValueError, "CovPredict: n must be in 1..256, got %d", n);
        return -1;
    }
    nn = (Py_ssize_t)n * n;
    if (get_doubles(A, nn, 0, &self->a_view, "A") < 0)
        return -1;
    if (get_doubles(Q, nn, 0, &self->q_view, "Q") < 0) {
        PyBuffer_Release(&self->a_view);
        return -1;
    }
    if (get_doubles(T, nn, 1, &self->t_view, "T") < 0) {
        PyBuffer_Release(&self->a_view);
        PyBuffer_Release(&self->q_view);
        return -1;
    }
    self->n = n;
    self->bound = 1;
    return 0;
}

/* predict(P): P <- A P A^T + Q in place */
static PyObject *CovPredict_predict(CovPredictObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "CovPredict: not bound");
        return NULL;
    }
    if (check_nargs("predict", nargs, 1) < 0)
        return NULL;
    if (get_doubles(args[0], (Py_ssize_t)self->n * self->n, 1, &pv, "P") < 0)
        return NULL;
    ct_covariance_predict(self->n, (const double *)self->a_view.buf, (double *)pv.buf,
                          (const double *)self->q_view.buf, (double *)self->t_view.buf);
    PyBuffer_Release(&pv);
    Py_RETURN_NONE;
}

static PyMethodDef CovPredict_methods[] = {
    {"predict", (PyCFunction)(void (*)(void))CovPredict_predict, METH_FASTCALL,
     "predict(P): P <- A P A^T + Q with the bound A and Q"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject CovPredictType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.CovPredict",
    .tp_basicsize = sizeof(CovPredictObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "CovPredict(n, A, Q, T): the covariance prediction bound to caller-owned A, Q and scratch T",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)CovPredict_init,
    .tp_dealloc = (destructor)CovPredict_dealloc,
    .tp_methods = CovPredict_methods,
};

/* ---------------------------------------------------------------- KUpdate */
#define KU_NBUF 16
typedef struct {
    PyObject_HEAD
    struct ct_kalman u;
    double *nis;
    Py_buffer views[KU_NBUF];
    int bound;
} KUpdateObject;

static void KUpdate_dealloc(KUpdateObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < KU_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int KUpdate_init(KUpdateObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "m", "H", "R", "y", "dx", "S", "Sinv", "K", "PHt", "T", "TH", "X", "KR",
                             "w", "L", "M", "nis", NULL};
    static const char *names[KU_NBUF] = {"H", "R", "y", "dx", "S", "Sinv", "K", "PHt", "T", "TH", "X",
                                         "KR", "w", "L", "M", "nis"};
    PyObject *o[KU_NBUF];
    double *ptr[KU_NBUF];
    int n, m, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiOOOOOOOOOOOOOOOO", kwlist, &n, &m, &o[0], &o[1], &o[2],
                                     &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11],
                                     &o[12], &o[13], &o[14], &o[15]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "KUpdate: already bound");
        return -1;
    }
    if (n < 1 || n > 256 || m < 1 || m > 64) {
        PyErr_Format(PyExc_ValueError, "KUpdate: n in 1..256 and m in 1..64, got %d, %d", n, m);
        return -1;
    }
    for (i = 0; i < KU_NBUF; ++i) {
        Py_ssize_t nn = (Py_ssize_t)n * n, nm = (Py_ssize_t)n * m, mm = (Py_ssize_t)m * m;
        /* H R y dx S Sinv K PHt T TH X KR w L M nis */
        static const int kind[KU_NBUF] = {1, 2, 3, 4, 2, 2, 1, 1, 0, 1, 0, 1, 3, 2, 2, 5};
        Py_ssize_t len = kind[i] == 0 ? nn : kind[i] == 1 ? nm : kind[i] == 2 ? mm : kind[i] == 3 ? m
                         : kind[i] == 4 ? n : 1;
        if (get_doubles(o[i], len, i >= 3, &self->views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        ptr[i] = (double *)self->views[i].buf;
    }
    ct_kalman_bind(&self->u, n, m, ptr);
    self->nis = ptr[15];
    self->bound = 1;
    return 0;
}

/* update(P, gate) -> flags (a small int: no object is created) */
static PyObject *KUpdate_update(KUpdateObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer pv;
    double gate;
    int flags;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "KUpdate: not bound");
        return NULL;
    }
    if (check_nargs("update", nargs, 2) < 0 || get_double(args[1], &gate) < 0)
        return NULL;
    if (get_doubles(args[0], (Py_ssize_t)self->u.n * self->u.n, 1, &pv, "P") < 0)
        return NULL;
    flags = ct_kalman_update(&self->u, (double *)pv.buf, gate, self->nis);
    PyBuffer_Release(&pv);
    return PyLong_FromLong(flags);
}

static PyMethodDef KUpdate_methods[] = {
    {"update", (PyCFunction)(void (*)(void))KUpdate_update, METH_FASTCALL,
     "update(P, gate) -> flags: one Kalman update of P with the bound H, R, y"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject KUpdateType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.KUpdate",
    .tp_basicsize = sizeof(KUpdateObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "KUpdate(n, m, H, R, y, dx, S, Sinv, K, PHt, T, TH, X, KR, w, L, M, nis): KalmanUpdate.update "
              "bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)KUpdate_init,
    .tp_dealloc = (destructor)KUpdate_dealloc,
    .tp_methods = KUpdate_methods,
};

/* ---------------------------------------------------------------- OriProp */
#define ORI_NBUF 6
typedef struct {
    PyObject_HEAD
    struct ct_ori o;
    Py_buffer views[ORI_NBUF];
    int bound;
} OriPropObject;

static void OriProp_dealloc(OriPropObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < ORI_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int OriProp_init(OriPropObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "theta", "bias", "dist", "R", "Rc", "A", "Q", "P", "T", NULL};
    static const char *names[ORI_NBUF] = {"R", "Rc", "A", "Q", "P", "T"};
    PyObject *o[ORI_NBUF];
    double *ptr[ORI_NBUF];
    int n, t0, b0, d0, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiiiOOOOOO", kwlist, &n, &t0, &b0, &d0, &o[0], &o[1], &o[2],
                                     &o[3], &o[4], &o[5]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "OriProp: already bound");
        return -1;
    }
    if (n < 9 || n > 256 || t0 < 0 || b0 < 0 || d0 < 0 || t0 + 3 > n || b0 + 3 > n || d0 + 3 > n) {
        PyErr_SetString(PyExc_ValueError, "OriProp: bad state size or row indices");
        return -1;
    }
    for (i = 0; i < ORI_NBUF; ++i) {
        if (get_doubles(o[i], i < 2 ? 9 : (Py_ssize_t)n * n, i != 0 && i != 3, &self->views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        ptr[i] = (double *)self->views[i].buf;
    }
    self->o.n = n;
    self->o.theta = t0;
    self->o.bias = b0;
    self->o.dist = d0;
    self->o.gyro_noise = 0.0;
    self->o.gyro_bias_rw = 0.0;
    self->o.R = ptr[0];
    self->o.Rc = ptr[1];
    self->o.A = ptr[2];
    self->o.Q = ptr[3];
    self->o.P = ptr[4];
    self->o.T = ptr[5];
    self->bound = 1;
    return 0;
}

/* propagate(dt_acc, dt2_acc, cd_acc, qd_acc, gyro_noise, gyro_bias_rw) */
static PyObject *OriProp_propagate(OriPropObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[6];
    int i;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "OriProp: not bound");
        return NULL;
    }
    if (check_nargs("propagate", nargs, 6) < 0)
        return NULL;
    for (i = 0; i < 6; ++i)
        if (get_double(args[i], &v[i]) < 0)
            return NULL;
    self->o.gyro_noise = v[4];
    self->o.gyro_bias_rw = v[5];
    ct_orientation_propagate(&self->o, v[0], v[1], v[2], v[3]);
    Py_RETURN_NONE;
}

static PyMethodDef OriProp_methods[] = {
    {"propagate", (PyCFunction)(void (*)(void))OriProp_propagate, METH_FASTCALL,
     "propagate(dt_acc, dt2_acc, cd_acc, qd_acc, gyro_noise, gyro_bias_rw): OrientationFilter.propagate's "
     "numeric body"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject OriPropType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.OriProp",
    .tp_basicsize = sizeof(OriPropObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "OriProp(n, theta, bias, dist, R, Rc, A, Q, P, T): the orientation "
              "filter's covariance propagation bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)OriProp_init,
    .tp_dealloc = (destructor)OriProp_dealloc,
    .tp_methods = OriProp_methods,
};

/* ---------------------------------------------------------------- InsStep */
#define INS_NBUF 9
typedef struct {
    PyObject_HEAD
    struct ct_ins s;
    double E[9];
    Py_buffer views[INS_NBUF];
    int bound;
} InsStepObject;

static void InsStep_dealloc(InsStepObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < INS_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int InsStep_init(InsStepObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "p", "v", "Th", "ba", "bg", "A", "P", "Q", "T", NULL};
    static const char *names[INS_NBUF] = {"p", "v", "Th", "ba", "bg", "A", "P", "Q", "T"};
    PyObject *o[INS_NBUF];
    double *ptr[INS_NBUF];
    int n, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOOOOO", kwlist, &n, &o[0], &o[1], &o[2], &o[3],
                                     &o[4], &o[5], &o[6], &o[7], &o[8]))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "InsStep: already bound");
        return -1;
    }
    if (n < CT_GYR + 3 || n > 256) {
        PyErr_Format(PyExc_ValueError, "InsStep: n must be in %d..256, got %d", CT_GYR + 3, n);
        return -1;
    }
    for (i = 0; i < INS_NBUF; ++i) {
        Py_ssize_t len = i == 2 ? 9 : (i < 5 ? 3 : (Py_ssize_t)n * n);
        if (get_doubles(o[i], len, i != 7, &self->views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            return -1;
        }
        ptr[i] = (double *)self->views[i].buf;
    }
    self->s.n = n;
    self->s.p = ptr[0];
    self->s.v = ptr[1];
    self->s.Th = ptr[2];
    self->s.ba = ptr[3];
    self->s.bg = ptr[4];
    self->s.A = ptr[5];
    self->s.P = ptr[6];
    self->s.Q = ptr[7];
    self->s.T = ptr[8];
    self->s.E = self->E;
    self->bound = 1;
    return 0;
}

/* propagate(dt, f0x, f0y, f0z, f1x, f1y, f1z, wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z, ka, kg) */
static PyObject *InsStep_propagate(InsStepObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double dt, in[15], ka, kg;
    int i;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "InsStep: not bound");
        return NULL;
    }
    if (check_nargs("propagate", nargs, 18) < 0 || get_double(args[0], &dt) < 0)
        return NULL;
    for (i = 0; i < 15; ++i)
        if (get_double(args[1 + i], &in[i]) < 0)
            return NULL;
    if (get_double(args[16], &ka) < 0 || get_double(args[17], &kg) < 0)
        return NULL;
    ct_ins_propagate(&self->s, dt, in, ka, kg);
    Py_RETURN_NONE;
}

static PyMethodDef InsStep_methods[] = {
    {"propagate", (PyCFunction)(void (*)(void))InsStep_propagate, METH_FASTCALL,
     "propagate(dt, f0 (3), f1 (3), w (3), r0 (3), r1 (3), ka, kg): one strapdown and covariance step"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject InsStepType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.InsStep",
    .tp_basicsize = sizeof(InsStepObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "InsStep(n, p, v, Th, ba, bg, A, P, Q, T): FusionFilter._propagate bound to one state's buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)InsStep_init,
    .tp_dealloc = (destructor)InsStep_dealloc,
    .tp_methods = InsStep_methods,
};

/* strapdown_rotate(R, ux, uy, uz): R <- R exp([u]x) in place (Strapdown.rotate; R a writable
 * C-contiguous float64 3x3) */
static PyObject *core_strapdown_rotate(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double u[3], E[9];
    Py_buffer rv;
    int k;
    (void)mod;
    if (check_nargs("strapdown_rotate", nargs, 4) < 0)
        return NULL;
    for (k = 0; k < 3; ++k)
        if (get_double(args[1 + k], &u[k]) < 0)
            return NULL;
    if (get_doubles(args[0], 9, 1, &rv, "R") < 0)
        return NULL;
    ct_strapdown_rotate((double *)rv.buf, u[0], u[1], u[2], E);
    PyBuffer_Release(&rv);
    Py_RETURN_NONE;
}

/* exp_rotvec(wx, wy, wz) -> 9-tuple, as linalg.exp_rotvec (for tests) */
static PyObject *core_exp_rotvec(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double w[3], out[9];
    PyObject *r;
    int k;
    (void)mod;
    if (check_nargs("exp_rotvec", nargs, 3) < 0)
        return NULL;
    for (k = 0; k < 3; ++k)
        if (get_double(args[k], &w[k]) < 0)
            return NULL;
    ct_exp_rotvec(w[0], w[1], w[2], out);
    r = PyTuple_New(9);
    if (r == NULL)
        return NULL;
    for (k = 0; k < 9; ++k) {
        PyObject *f = PyFloat_FromDouble(out[k]);
        if (f == NULL) {
            Py_DECREF(r);
            return NULL;
        }
        PyTuple_SET_ITEM(r, k, f);
    }
    return r;
}

/* pose_frame(seq, src, node, t_us, px, py, pz, qw, qx, qy, qz, v0..v5, status, quality) -> bytes or None:
 * one POSE frame as encode_frame makes it (None: a value the wire format refuses) */
static PyObject *core_pose_frame(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    uint8_t out[CT_POSE_FRAME_MAX];
    double v[13];
    long long ints[3];
    unsigned long long t_us;
    int k, seq, src;
    static const int int_at[3] = {2, 17, 18};
    (void)mod;
    if (check_nargs("pose_frame", nargs, 19) < 0)
        return NULL;
    seq = (int)PyLong_AsLong(args[0]);
    src = (int)PyLong_AsLong(args[1]);
    if (PyErr_Occurred())
        return NULL;
    /* a field struct.pack would refuse (out of range, not an integer, not a float): None, as the
     * Python counts a tx error for any encoding error */
    if (ct_py_pose_ints(args, int_at, ints, &t_us))
        Py_RETURN_NONE;
    for (k = 0; k < 13; ++k)
        if (get_double(args[4 + k], &v[k]) < 0) {
            PyErr_Clear();
            Py_RETURN_NONE;
        }
    k = ct_pose_frame(out, seq, src, ints[0], (uint64_t)t_us, v, ints[1], ints[2]);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

/* ---------------------------------------------------------------- ImuDelta */
/* a C-contiguous int64 buffer of at least n items, writable, or -1 with TypeError naming `what` */
static int get_int64s(PyObject *obj, Py_ssize_t n, Py_buffer *view, const char *what)
{
    return ct_py_buffer(obj, n, 8, "ql", 1, view, what);
}

typedef struct {
    PyObject_HEAD
    Py_buffer st_view, io_view, out_view;
    double interval_us, step_us;
    int bound;
} ImuDeltaObject;

static void ImuDelta_dealloc(ImuDeltaObject *self)
{
    if (self->bound) {
        PyBuffer_Release(&self->st_view);
        PyBuffer_Release(&self->io_view);
        PyBuffer_Release(&self->out_view);
    }
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ImuDelta_init(ImuDeltaObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"st", "io", "out", "interval_us", "step_us", NULL};
    PyObject *st, *io, *out;
    double interval_us, step_us;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOdd", kwlist, &st, &io, &out, &interval_us, &step_us))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ImuDelta: already bound");
        return -1;
    }
    if (get_int64s(st, 256 * CT_DELTA_NST, &self->st_view, "st") < 0)
        return -1;
    if (get_int64s(io, CT_DIO_N, &self->io_view, "io") < 0) {
        PyBuffer_Release(&self->st_view);
        return -1;
    }
    if (get_doubles(out, 7, 1, &self->out_view, "out") < 0) {
        PyBuffer_Release(&self->st_view);
        PyBuffer_Release(&self->io_view);
        return -1;
    }
    self->interval_us = interval_us;
    self->step_us = step_us;
    self->bound = 1;
    return 0;
}

/* feed(msg, now_us) -> n: one IMU_DELTA message (node, x, y, z, stamp) */
static PyObject *ImuDelta_feed(ImuDeltaObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long v[5], now;
    int k, n;
    if (!self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "ImuDelta: not bound");
        return NULL;
    }
    if (check_nargs("feed", nargs, 2) < 0)
        return NULL;
    if (!PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != 5) {
        PyErr_SetString(PyExc_TypeError, "feed: msg must be an IMU_DELTA (a 5-tuple)");
        return NULL;
    }
    for (k = 0; k < 5; ++k) {
        v[k] = PyLong_AsLongLong(PyTuple_GET_ITEM(args[0], k));
        if (v[k] == -1 && PyErr_Occurred())
            return NULL;
    }
    now = PyLong_AsLongLong(args[1]);
    if (now == -1 && PyErr_Occurred())
        return NULL;
    if (v[0] < 0 || v[0] > 255) {
        PyErr_SetString(PyExc_ValueError, "feed: node outside 0..255");
        return NULL;
    }
    n = ct_imu_delta((int64_t *)self->st_view.buf + v[0] * CT_DELTA_NST, v[1], v[2], v[3], v[4], now,
                     self->interval_us, self->step_us, (double *)self->out_view.buf, (int64_t *)self->io_view.buf);
    return PyLong_FromLong(n);
}

static PyMethodDef ImuDelta_methods[] = {
    {"feed", (PyCFunction)(void (*)(void))ImuDelta_feed, METH_FASTCALL,
     "feed(msg, now_us) -> n: Receiver._delta for one IMU_DELTA message"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ImuDeltaType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ImuDelta",
    .tp_basicsize = sizeof(ImuDeltaObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ImuDelta(st, io, out, interval_us, step_us): the receiver's IMU_DELTA pairs bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ImuDelta_init,
    .tp_dealloc = (destructor)ImuDelta_dealloc,
    .tp_methods = ImuDelta_methods,
};

/* imu_clipped(msg) -> bool: an IMU_SAMPLE (node, t_us, ax, ay, az, gx, gy, gz) with an axis clipped */
static PyObject *core_imu_clipped(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t v[6];
    int k;
    (void)mod;
    if (check_nargs("imu_clipped", nargs, 1) < 0)
        return NULL;
    if (!PyTuple_Check(args[0]) || PyTuple_GET_SIZE(args[0]) != 8) {
        PyErr_SetString(PyExc_TypeError, "imu_clipped: msg must be an IMU_SAMPLE (an 8-tuple)");
        return NULL;
    }
    for (k = 0; k < 6; ++k) {
        long long x = PyLong_AsLongLong(PyTuple_GET_ITEM(args[0], 2 + k));
        if (x == -1 && PyErr_Occurred())
            return NULL;
        v[k] = x;
    }
    if (ct_imu_clipped(v))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* ------------------------------------------------------- module functions */
static PyObject *point_tuple(const double *t, int jac)
{
    int k, m = jac ? 9 : 3;
    PyObject *r = PyTuple_New(m);
    if (r == NULL)
        return NULL;
    for (k = 0; k < m; ++k) {
        PyObject *f = PyFloat_FromDouble(t[k]);
        if (f == NULL) {
            Py_DECREF(r);
            return NULL;
        }
        PyTuple_SET_ITEM(r, k, f);
    }
    return r;
}

/* loop_point(x, y, z, radius, scale, jac) -> tuple, as field.loop_point (for tests and tools) */
static PyObject *core_loop_point(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double v[5], t[9];
    int k, jac;
    (void)mod;
    if (check_nargs("loop_point", nargs, 6) < 0)
        return NULL;
    for (k = 0; k < 5; ++k)
        if (get_double(args[k], &v[k]) < 0)
            return NULL;
    if ((jac = PyObject_IsTrue(args[5])) < 0)
        return NULL;
    ct_loop_point(v[0], v[1], v[2], v[3], v[4], jac, t);
    return point_tuple(t, jac);
}

/* dipole_point(px, py, pz, mx, my, mz, jac) -> tuple, as field.dipole_point */
static PyObject *core_dipole_point(PyObject *mod, PyObject *const *args, Py_ssize_t nargs)
{
    double v[6], t[9];
    int k, jac;
    (void)mod;
    if (check_nargs("dipole_point", nargs, 7) < 0)
        return NULL;
    for (k = 0; k < 6; ++k)
        if (get_double(args[k], &v[k]) < 0)
            return NULL;
    if ((jac = PyObject_IsTrue(args[6])) < 0)
        return NULL;
    ct_dipole_point(v[0], v[1], v[2], v[3], v[4], v[5], jac, t);
    return point_tuple(t, jac);
}

static PyMethodDef core_methods[] = {
    {"imu_clipped", (PyCFunction)(void (*)(void))core_imu_clipped, METH_FASTCALL,
     "imu_clipped(msg): an IMU_SAMPLE with an axis at the clip code (receive._clipped)"},
    {"pose_frame", (PyCFunction)(void (*)(void))core_pose_frame, METH_FASTCALL,
     "pose_frame(seq, src, node, t_us, px, py, pz, qw, qx, qy, qz, v0, .., v5, status, quality): one POSE "
     "frame as protocol.framing.encode_frame makes it, or None where struct.pack refuses a value"},
    {"loop_point", (PyCFunction)(void (*)(void))core_loop_point, METH_FASTCALL,
     "loop_point(x, y, z, radius, scale, jac): as coiltrack.firmware.model.field.loop_point"},
    {"strapdown_rotate", (PyCFunction)(void (*)(void))core_strapdown_rotate, METH_FASTCALL,
     "strapdown_rotate(R, ux, uy, uz): R <- R exp([u]x), as Strapdown.rotate"},
    {"exp_rotvec", (PyCFunction)(void (*)(void))core_exp_rotvec, METH_FASTCALL,
     "exp_rotvec(wx, wy, wz): exp([w]x) row-major, as coiltrack.firmware.linalg.exp_rotvec"},
    {"dipole_point", (PyCFunction)(void (*)(void))core_dipole_point, METH_FASTCALL,
     "dipole_point(px, py, pz, mx, my, mz, jac): as coiltrack.firmware.model.field.dipole_point"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef core_module = {
    PyModuleDef_HEAD_INIT, "_core",
    "The compiled core of the coiltrack firmware (C99 kernels; the Python modules are the reference).",
    -1, core_methods, NULL, NULL, NULL, NULL};

/* each area's glue (py_<area>.c) adds its types and constants to the module */
int ct_register_window(PyObject *m);
int ct_register_fusimu(PyObject *m);
int ct_register_fusion(PyObject *m);
int ct_register_ac(PyObject *m);
int ct_register_rxdecode(PyObject *m);
int ct_register_single_coil(PyObject *m);
int ct_register_finish(PyObject *m);
int ct_register_multi(PyObject *m);
int ct_register_burst_open(PyObject *m);
int ct_register_solve(PyObject *m);
int ct_register_supervise(PyObject *m);
int ct_register_report(PyObject *m);
int ct_register_sc_choose(PyObject *m);
int ct_register_sc_window(PyObject *m);
int ct_register_sc_close(PyObject *m);
int ct_register_fuse(PyObject *m);
int ct_register_begin(PyObject *m);
int ct_register_periodic(PyObject *m);
int ct_register_ahead(PyObject *m);
int ct_register_acquire(PyObject *m);
static int (*const AREAS[])(PyObject *) = {
    ct_register_window, ct_register_fusimu, ct_register_fusion, ct_register_ac, ct_register_rxdecode,
    ct_register_single_coil,
    ct_register_finish,
    ct_register_multi,
    ct_register_burst_open,
    ct_register_solve,
    ct_register_supervise,
    ct_register_report,
    ct_register_sc_choose,
    ct_register_sc_window,
    ct_register_sc_close,
    ct_register_fuse,
    ct_register_begin,
    ct_register_periodic,
    ct_register_ahead,
    ct_register_acquire,
};

PyMODINIT_FUNC PyInit__core(void)
{
    PyObject *m;
    if (PyType_Ready(&SignalType) < 0 || PyType_Ready(&CovPredictType) < 0 || PyType_Ready(&InsStepType) < 0 ||
        PyType_Ready(&KUpdateType) < 0 || PyType_Ready(&OriPropType) < 0 ||
        PyType_Ready(&ImuDeltaType) < 0)
        return NULL;
    m = PyModule_Create(&core_module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&SignalType);
    if (PyModule_AddObject(m, "Signal", (PyObject *)&SignalType) < 0) {
        Py_DECREF(&SignalType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&CovPredictType);
    if (PyModule_AddObject(m, "CovPredict", (PyObject *)&CovPredictType) < 0) {
        Py_DECREF(&CovPredictType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&OriPropType);
    if (PyModule_AddObject(m, "OriProp", (PyObject *)&OriPropType) < 0) {
        Py_DECREF(&OriPropType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&KUpdateType);
    if (PyModule_AddObject(m, "KUpdate", (PyObject *)&KUpdateType) < 0) {
        Py_DECREF(&KUpdateType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&InsStepType);
    if (PyModule_AddObject(m, "InsStep", (PyObject *)&InsStepType) < 0) {
        Py_DECREF(&InsStepType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&ImuDeltaType);
    if (PyModule_AddObject(m, "ImuDelta", (PyObject *)&ImuDeltaType) < 0) {
        Py_DECREF(&ImuDeltaType);
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddIntConstant(m, "DELTA_NST", CT_DELTA_NST) < 0 || PyModule_AddIntConstant(m, "DIO_N", CT_DIO_N) < 0 ||
        PyModule_AddIntConstant(m, "IMU_CLIP", CT_IMU_CLIP) < 0 ||
        PyModule_AddIntConstant(m, "STAMP_LEAD_US", CT_STAMP_LEAD_US) < 0 ||
        PyModule_AddIntConstant(m, "STAMP_DVEL", CT_STAMP_DVEL) < 0 ||
        PyModule_AddIntConstant(m, "STAMP_SATURATED", CT_STAMP_SATURATED) < 0 ||
        PyModule_AddIntConstant(m, "STAMP_MASK", CT_STAMP_MASK) < 0 ||
        PyModule_AddIntConstant(m, "STAMP_LSB_US", CT_STAMP_LSB_US) < 0 ||
        PyModule_AddIntConstant(m, "POSE_ID", CT_POSE_ID) < 0 ||
        PyModule_AddIntConstant(m, "POSE_PAYLOAD", CT_POSE_PAYLOAD) < 0 ||
        PyModule_AddIntConstant(m, "POSE_CRC_EXTRA", CT_POSE_CRC_EXTRA) < 0 ||
        PyModule_AddIntConstant(m, "LM_NST", CT_LM_NST) < 0 || PyModule_AddIntConstant(m, "POS", CT_POS) < 0 || PyModule_AddIntConstant(m, "VEL", CT_VEL) < 0 ||
        PyModule_AddIntConstant(m, "ORI", CT_ORI) < 0 || PyModule_AddIntConstant(m, "ACC", CT_ACC) < 0 ||
        PyModule_AddIntConstant(m, "GYR", CT_GYR) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddIntConstant(m, "COIL_STRIDE", CT_COIL_STRIDE) < 0 ||
        PyModule_AddIntConstant(m, "KIND_LOOP", CT_KIND_LOOP) < 0 ||
        PyModule_AddIntConstant(m, "KIND_LOOP_AXES", CT_KIND_LOOP_AXES) < 0 ||
        PyModule_AddIntConstant(m, "KIND_DIPOLE", CT_KIND_DIPOLE) < 0 ||
        PyModule_AddIntConstant(m, "MAX_COILS", CT_MAX_COILS) < 0) {
        Py_DECREF(m);
        return NULL;
    }
#ifndef CT_SOURCE_HASH
#define CT_SOURCE_HASH "unknown"
#endif
    if (PyModule_AddStringConstant(m, "SOURCE_HASH", CT_SOURCE_HASH) < 0) { /* setup.py: sources.py */
        Py_DECREF(m);
        return NULL;
    }
    for (size_t i = 0; i < sizeof AREAS / sizeof AREAS[0]; i++) {
        if (AREAS[i](m) < 0) {
            Py_DECREF(m);
            return NULL;
        }
    }
    return m;
}
