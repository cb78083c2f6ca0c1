/*
 * CPython glue of the start of a burst's fusion update (src/fuse.c): the type FuseComp, bound once
 * (start-up) to one sensor's buffers (SensorInertial's, its fusion filter's live covariance, history
 * and flags, its channel's signals and pulse times, the tracker's currents, the re-solving solver's
 * model); its per-call method (METH_FASTCALL) takes the budget and creates no Python object (the
 * small int it returns is the interpreter's cached one).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

#define FZ_NBUF 26
static const char *fz_names[FZ_NBUF] = {"S", "S_comp", "h_ref", "h_j", "p_ref", "R_ref", "p_j", "R_j", "P", "hist_t",
                                        "hist_d", "hc", "fs", "tr", "pulse_t", "geom", "B", "J", "cur", "fz",
                                        "position", "rotation", "covariance", "mag_position", "mag_rotation",
                                        "mag_cov"};
/* lengths: > 0 in units of n, < 0 a fixed count, 0 set below (n_st^2, cap, cap * width, FS) */
static const int fz_per_n[FZ_NBUF] = {3, 3, 3, 3, -3, -9, -3, -9, 0, 0, 0, -2, 0, -1, 1, CT_COIL_STRIDE, 3, 9, 1,
                                      -CT_FZ_N, -3, -9, -36, -3, -9, -36};
static const int fz_wr[FZ_NBUF] = {0, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 1, 1};
static const int fz_i64[FZ_NBUF] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 1, 1, 1, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0};

typedef struct {
    PyObject_HEAD
    struct ct_fuse z;
    const double *sol[3];       /* the solver's results: position, rotation, covariance */
    double *mag[3];             /* the burst's magnetic-only solution kept for the update */
    Py_buffer views[FZ_NBUF];
    int bound;
} FuseCompObject;

static void FuseComp_dealloc(FuseCompObject *self)
{
    int i;
    if (self->bound)
        for (i = 0; i < FZ_NBUF; ++i)
            PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int FuseComp_init(FuseCompObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "n_st", "max_sigma", "motion_compensation", "fs_init", "fs_n", "buffers", NULL};
    PyObject *bufs, *seq;
    void *ptr[FZ_NBUF];
    struct ct_fuse *z = &self->z;
    int n, n_st, mc, fs_init, fs_n, i;
    double max_sigma;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iidpiiO", kwlist, &n, &n_st, &max_sigma, &mc, &fs_init, &fs_n, &bufs))
        return -1;
    if (self->bound) {
        PyErr_SetString(PyExc_RuntimeError, "FuseComp: already bound");
        return -1;
    }
    if (n < 1 || n > CT_FZ_MAXN || n_st < 1 || n_st > 256 || fs_init < 0 || fs_init >= fs_n) {
        PyErr_SetString(PyExc_ValueError, "FuseComp: bad pulse count, state size or flag index");
        return -1;
    }
    seq = PySequence_Fast(bufs, "FuseComp: buffers must be a sequence");
    if (seq == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(seq) != FZ_NBUF) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "FuseComp: needs %d buffers", FZ_NBUF);
        return -1;
    }
    for (i = 0; i < FZ_NBUF; ++i) {
        Py_ssize_t len = fz_per_n[i] > 0 ? (Py_ssize_t)fz_per_n[i] * n : -(Py_ssize_t)fz_per_n[i];
        if (i == 8)
            len = (Py_ssize_t)n_st * n_st;
        else if (i == 10)
            len = (Py_ssize_t)z->cap * CT_HIST_WIDTH;
        else if (i == 12)
            len = fs_n;
        else if (i == 9)
            len = 1;
        if (ct_py_buffer(PySequence_Fast_GET_ITEM(seq, i), len, 8, fz_i64[i] ? "ql" : "d", fz_wr[i], &self->views[i],
                         fz_names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&self->views[i]);
            Py_DECREF(seq);
            return -1;
        }
        ptr[i] = self->views[i].buf;
        if (i == 9)
            z->cap = (int64_t)(self->views[i].len / 8);
    }
    Py_DECREF(seq);
    z->n = n;
    z->n_st = n_st;
    z->motion_compensation = mc;
    z->fs_init = fs_init;
    z->max_sigma = max_sigma;
    z->S = ptr[0];
    z->S_comp = ptr[1];
    z->h_ref = ptr[2];
    z->h_j = ptr[3];
    z->p_ref = ptr[4];
    z->R_ref = ptr[5];
    z->p_j = ptr[6];
    z->R_j = ptr[7];
    z->P = ptr[8];
    z->ht = ptr[9];
    z->hd = ptr[10];
    z->hc = ptr[11];
    z->fs = ptr[12];
    z->tr = ptr[13];
    z->pulse_t = ptr[14];
    z->geom = ptr[15];
    z->B = ptr[16];
    z->J = ptr[17];
    z->cur = ptr[18];
    z->fz = ptr[19];
    for (i = 0; i < 3; ++i) {
        self->sol[i] = ptr[20 + i];
        self->mag[i] = ptr[23 + i];
    }
    self->bound = 1;
    return 0;
}

/* run(budget) -> code | waiting << 2 | used << 3 (ct_fuse_compensate) */
static PyObject *FuseComp_run(FuseCompObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t budget, used = 0;
    int waiting = 0, code;
    const struct ct_fuse *z = &self->z;
    if (!self->bound || ct_py_nargs("run", nargs, 1) < 0 || ct_py_int64(args[0], &budget) < 0)
        return NULL;
    if (z->hc[0] < 0 || z->hc[0] >= z->cap || z->hc[1] < 0 || z->hc[1] > z->cap || z->fz[CT_FZ_COMP_J] < 0 ||
        z->fz[CT_FZ_COMP_J] > z->n) {
        PyErr_SetString(PyExc_ValueError, "FuseComp.run: the history's head or count, or the next pulse, out of range");
        return NULL;
    }
    code = ct_fuse_compensate(z, budget, &used, &waiting);
    return PyLong_FromLongLong((long long)code | ((long long)waiting << 2) | ((long long)used << 3));
}

/* solution(solved) -> solved: SensorInertial.on_solution's copies and stage (the caller sets pending) */
static PyObject *FuseComp_solution(FuseCompObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int solved;
    if (!self->bound || ct_py_nargs("solution", nargs, 1) < 0)
        return NULL;
    solved = PyObject_IsTrue(args[0]);
    if (solved < 0)
        return NULL;
    if (!solved)
        Py_RETURN_FALSE;
    ct_fuse_solution(self->sol[0], self->sol[1], self->sol[2], self->mag[0], self->mag[1], self->mag[2], self->z.fz);
    Py_RETURN_TRUE;
}

static PyMethodDef FuseComp_methods[] = {
    {"solution", (PyCFunction)(void (*)(void))FuseComp_solution, METH_FASTCALL,
     "solution(solved) -> solved: SensorInertial.on_solution's copies of the solver's results and its stage"},
    {"run", (PyCFunction)(void (*)(void))FuseComp_run, METH_FASTCALL,
     "run(budget) -> code | waiting << 2 | used << 3: SensorInertial.fuse's compensation stages (code: 0 no room, "
     "1 the re-solve to begin, 2 past the compensation)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FuseCompType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FuseComp",
    .tp_basicsize = sizeof(FuseCompObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FuseComp(n, n_st, max_sigma, motion_compensation, fs_init, fs_n, buffers): one sensor's motion "
              "compensation of a burst (the start of its fusion update) bound to its buffers",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FuseComp_init,
    .tp_dealloc = (destructor)FuseComp_dealloc,
    .tp_methods = FuseComp_methods,
};

int ct_register_fuse(PyObject *m)
{
    if (ct_py_add_type(m, &FuseCompType, "FuseComp") < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "FZ_N", CT_FZ_N) < 0)
        return -1;
    return 0;
}
