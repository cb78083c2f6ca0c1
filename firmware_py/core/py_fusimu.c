/*
 * The CPython glue of core/src/fusimu.c (the per-IMU-sample path of the fused trackers):
 *
 *   FusPred(n, p, v, Th, ba, bg, A, P, Q, T, itv, idv, st, tau_a, tau_g, qv_k, gyro_noise, qa_k,
 *           qg_k, moving)
 *       .propagate(k, nring, t0, t1)      InertialPrediction.propagate of the bound state
 *       .history(hd, h, k)                InertialPrediction.history's row (to_source)
 *       .advance(k, nring, t0, t1, hd, h) both (InertialPrediction.advance)
 *   FusRow(idv, moving).store(k, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi)
 *                                         InertialPrediction.push's row
 *   FusOutput(n, P, Th, idv, hd, od, moving, stale_us, dr_after_us, dr_limit_us)
 *       .queue(slot, h, k, age, recovering, inconsistent)   PoseOutput.queue's row
 *       .report(slot, p, q, var) -> status                  PoseOutput.into_report's copy
 *   FusLive(pred, row, out, hd).sample(k, nring, t0, t1, h, o, age, recovering, inconsistent, f, w, fsrc, Phi)
 *                                         FusRow.store, FusPred.advance, FusOutput.queue in one call
 *   OriPred(R, bias, dist, acc, st, dist_corr, acc_corr_time_s)
 *       .predict(dt, wx, wy, wz, qwd)     OrientationFilter.predict after its time step
 *   OriUpd(n, theta, bias, dist, R, Rc, b, d, a, sums, incl y/H/R/dx, compass y/H/R/dx, h_g, cst, params)
 *       .acc_begin / .acc_end / .mag_fill / .mag_apply   the orientation updates around ct_kalman_update
 *
 *   QuietSample(t, flags, starts, ends, before, after).find(head, count, after_t, t_imu, max_age_us)
 *                                         track.burst_fusion.quiet_sample
 *   ImuPush(t, d, hc, st, acc_lsb, gyr_lsb).push(msg)
 *                                         measure.imu.ImuRing.push (ct_imu_ring_push)
 *
 * The arrays are bound once (buffer protocol) at construction; the per-call methods are
 * METH_FASTCALL, read their numbers in place and create no Python object (they return None).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"
#include "py_fusion.h"

#define FUS_MAXBUF 16

/* the bound buffers of one object */
typedef struct {
    Py_buffer v[FUS_MAXBUF];
    int n;
} fus_views;

static void fus_release(fus_views *b)
{
    while (b->n > 0)
        PyBuffer_Release(&b->v[--b->n]);
}

/* bind obj as a C-contiguous buffer of at least `count` items of `fmt` ('d' or 'q'); its pointer */
static void *fus_bind(fus_views *b, PyObject *obj, Py_ssize_t count, char fmt, int writable, const char *what)
{
    if (b->n >= FUS_MAXBUF) {
        PyErr_Format(PyExc_RuntimeError, "%s: more than %d buffers bound", what, FUS_MAXBUF);
        return NULL;
    }
    if (ct_py_buffer(obj, count, 8, fmt == 'd' ? "d" : "ql", writable, &b->v[b->n], what) < 0)
        return NULL;
    return b->v[b->n++].buf;
}

static int fus_double(PyObject *o, double *x)
{
    return ct_py_double(o, x);
}

static int fus_long(PyObject *o, long long *x)
{
    *x = PyLong_AsLongLong(o);
    return (*x == -1 && PyErr_Occurred()) ? -1 : 0;
}

static int fus_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    return ct_py_nargs(name, nargs, want);
}

/* a slot index within 0..cap-1 */
static int fus_slot(PyObject *o, int cap, int *k, const char *what)
{
    long long x;
    if (fus_long(o, &x) < 0)
        return -1;
    if (x < 0 || x >= cap) {
        PyErr_Format(PyExc_IndexError, "%s: slot %lld outside 0..%d", what, x, cap - 1);
        return -1;
    }
    *k = (int)x;
    return 0;
}

/* a 3x3 matrix (array or memoryview, 2-D (3, 3) or flat (9,), any strides) into r[9] */
static int fus_matrix3(PyObject *obj, double *r)
{
    Py_buffer v;
    const char *f;
    int i, k;
    if (PyObject_GetBuffer(obj, &v, PyBUF_RECORDS_RO) < 0)
        return -1;
    f = v.format;
    if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<'))
        f++;
    if (f == NULL || v.itemsize != 8 || f[0] != 'd' || f[1] != '\0' ||
        !((v.ndim == 2 && v.shape[0] == 3 && v.shape[1] == 3) || (v.ndim == 1 && v.shape[0] == 9))) {
        PyBuffer_Release(&v);
        PyErr_SetString(PyExc_TypeError, "Phi: needs a float64 buffer of shape (3, 3) or (9,)");
        return -1;
    }
    if (v.ndim == 2) {
        for (i = 0; i < 3; ++i)
            for (k = 0; k < 3; ++k)
                memcpy(&r[3 * i + k], (const char *)v.buf + i * v.strides[0] + k * v.strides[1], sizeof(double));
    } else {
        for (i = 0; i < 9; ++i)
            memcpy(&r[i], (const char *)v.buf + i * v.strides[0], sizeof(double));
    }
    PyBuffer_Release(&v);
    return 0;
}

#define FUS_DEALLOC(T)                                                   \
    static void T##_dealloc(T##Object *self)                             \
    {                                                                    \
        fus_release(&self->views);                                       \
        Py_TYPE(self)->tp_free((PyObject *)self);                        \
    }

#define FUS_TYPE(T, NAME, DOC)                                           \
    static PyTypeObject T##Type = {                                      \
        PyVarObject_HEAD_INIT(NULL, 0)                                   \
        .tp_name = "coiltrack.firmware._core." NAME,                     \
        .tp_basicsize = sizeof(T##Object),                               \
        .tp_flags = Py_TPFLAGS_DEFAULT,                                  \
        .tp_doc = DOC,                                                   \
        .tp_new = PyType_GenericNew,                                     \
        .tp_init = (initproc)T##_init,                                   \
        .tp_dealloc = (destructor)T##_dealloc,                           \
        .tp_methods = T##_methods,                                       \
    };

static int fus_fresh(fus_views *b, const char *name)
{
    if (b->n) {
        PyErr_Format(PyExc_RuntimeError, "%s: already bound", name);
        return -1;
    }
    return 0;
}

/* ---------------------------------------------------------------- FusPred */
typedef struct {
    PyObject_HEAD
    struct ct_fus_pred f;
    double E[9];
    int moving;
    fus_views views;
} FusPredObject;

FUS_DEALLOC(FusPred)

static int FusPred_init(FusPredObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "p", "v", "Th", "ba", "bg", "A", "P", "Q", "T", "itv", "idv", "st", "tau_a",
                             "tau_g", "qv_k", "gyro_noise", "qa_k", "qg_k", "moving", NULL};
    PyObject *o[13];
    struct ct_fus_pred *f = &self->f;
    struct ct_ins *s = &f->ins;
    Py_ssize_t nn, cap;
    int n, moving;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOOOOOOOOddddddp", kwlist, &n, &o[0], &o[1], &o[2], &o[3],
                                     &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &f->dtk[0],
                                     &f->dtk[1], &f->dtk[2], &f->dtk[3], &f->dtk[4], &f->dtk[5], &moving))
        return -1;
    if (fus_fresh(&self->views, "FusPred") < 0)
        return -1;
    if (n < CT_GYR + 3 || n > 256) {
        PyErr_Format(PyExc_ValueError, "FusPred: n must be in %d..256, got %d", CT_GYR + 3, n);
        return -1;
    }
    nn = (Py_ssize_t)n * n;
    if (PyObject_Length(o[9]) < 2) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "FusPred: itv needs at least 2 entries");
        return -1;
    }
    cap = PyObject_Length(o[9]);
    if (!(s->p = fus_bind(&self->views, o[0], 3, 'd', 1, "p")) ||
        !(s->v = fus_bind(&self->views, o[1], 3, 'd', 1, "v")) ||
        !(s->Th = fus_bind(&self->views, o[2], 9, 'd', 1, "Th")) ||
        !(s->ba = fus_bind(&self->views, o[3], 3, 'd', 1, "ba")) ||
        !(s->bg = fus_bind(&self->views, o[4], 3, 'd', 1, "bg")) ||
        !(s->A = fus_bind(&self->views, o[5], nn, 'd', 1, "A")) ||
        !(s->P = fus_bind(&self->views, o[6], nn, 'd', 1, "P")) ||
        !(f->Q = fus_bind(&self->views, o[7], nn, 'd', 1, "Q")) ||
        !(s->T = fus_bind(&self->views, o[8], nn, 'd', 1, "T")) ||
        !(f->itv = fus_bind(&self->views, o[9], cap, 'q', 0, "itv")) ||
        !(f->idv = fus_bind(&self->views, o[10], cap * CT_IMU_WIDTH, 'd', 0, "idv")) ||
        !(f->st = fus_bind(&self->views, o[11], CT_FS_NST, 'd', 1, "st"))) {
        fus_release(&self->views);
        return -1;
    }
    s->n = n;
    s->Q = f->Q;
    s->E = self->E;
    f->icap = (int)cap;
    self->moving = moving;
    return 0;
}

/* propagate(k, nring, t0, t1) */
static PyObject *FusPred_propagate(FusPredObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long nring, t0, t1;
    int k;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusPred: not bound");
        return NULL;
    }
    if (fus_nargs("propagate", nargs, 4) < 0 || fus_slot(args[0], self->f.icap, &k, "propagate") < 0 ||
        fus_long(args[1], &nring) < 0 || fus_long(args[2], &t0) < 0 || fus_long(args[3], &t1) < 0)
        return NULL;
    ct_fus_propagate(&self->f, k, (int)nring, (int64_t)t0, (int64_t)t1);
    Py_RETURN_NONE;
}

/* history(hd, h, k): row h of the history rows hd = the bound state in the source frame */
static PyObject *FusPred_history(FusPredObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer hv;
    int k;
    long long h;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusPred: not bound");
        return NULL;
    }
    if (fus_nargs("history", nargs, 3) < 0 || fus_long(args[1], &h) < 0 ||
        fus_slot(args[2], self->f.icap, &k, "history") < 0)
        return NULL;
    if (PyObject_GetBuffer(args[0], &hv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0)
        return NULL;
    if (hv.itemsize != 8 || h < 0 || (h + 1) * CT_HIST_WIDTH * 8 > hv.len) {
        PyBuffer_Release(&hv);
        PyErr_SetString(PyExc_IndexError, "history: row outside the history buffer");
        return NULL;
    }
    ct_fus_to_source(self->f.idv + (long)k * CT_IMU_WIDTH, self->moving, self->f.ins.p, self->f.ins.Th,
                     (double *)hv.buf + h * CT_HIST_WIDTH);
    PyBuffer_Release(&hv);
    Py_RETURN_NONE;
}

/* advance(k, nring, t0, t1, hd, h): propagate(k, nring, t0, t1) then history(hd, h, k) */
static PyObject *FusPred_advance(FusPredObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    PyObject *r;
    if (fus_nargs("advance", nargs, 6) < 0)
        return NULL;
    r = FusPred_propagate(self, args, 4);
    if (r == NULL)
        return NULL;
    Py_DECREF(r);
    {
        PyObject *h[3] = {args[4], args[5], args[0]};
        return FusPred_history(self, h, 3);
    }
}

static PyMethodDef FusPred_methods[] = {
    {"advance", (PyCFunction)(void (*)(void))FusPred_advance, METH_FASTCALL,
     "advance(k, nring, t0, t1, hd, h): propagate, then history row h of hd"},
    {"propagate", (PyCFunction)(void (*)(void))FusPred_propagate, METH_FASTCALL,
     "propagate(k, nring, t0, t1): InertialPrediction.propagate of the bound state"},
    {"history", (PyCFunction)(void (*)(void))FusPred_history, METH_FASTCALL,
     "history(hd, h, k): history row h of hd from the bound state (Phi of IMU row k)"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(FusPred, "FusPred", "FusPred(n, p, v, Th, ba, bg, A, P, Q, T, itv, idv, st, tau_a, tau_g, qv_k, "
         "gyro_noise, qa_k, qg_k, moving): the fusion filter's step bound to one state and the IMU ring")

/* ----------------------------------------------------------------- FusRow */
typedef struct {
    PyObject_HEAD
    double *idv;
    int cap, moving;
    fus_views views;
} FusRowObject;

FUS_DEALLOC(FusRow)

static int FusRow_init(FusRowObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"idv", "cap", "moving", NULL};
    PyObject *d;
    int cap, moving;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "Oip", kwlist, &d, &cap, &moving))
        return -1;
    if (fus_fresh(&self->views, "FusRow") < 0)
        return -1;
    if (cap < 2) {
        PyErr_SetString(PyExc_ValueError, "FusRow: cap must be >= 2");
        return -1;
    }
    if (!(self->idv = fus_bind(&self->views, d, (Py_ssize_t)cap * CT_IMU_WIDTH, 'd', 1, "idv")))
        return -1;
    self->cap = cap;
    self->moving = moving;
    return 0;
}

/* store(k, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) */
static PyObject *FusRow_store(FusRowObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[9], phi[9], *row;
    int k, i;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusRow: not bound");
        return NULL;
    }
    if (fus_nargs("store", nargs, 11) < 0 || fus_slot(args[0], self->cap, &k, "store") < 0)
        return NULL;
    for (i = 0; i < 9; ++i)
        if (fus_double(args[1 + i], &v[i]) < 0)
            return NULL;
    if (self->moving && fus_matrix3(args[10], phi) < 0)
        return NULL;
    row = self->idv + (long)k * CT_IMU_WIDTH;
    for (i = 0; i < 9; ++i)
        row[CT_IMU_F + i] = v[i];
    if (self->moving)
        for (i = 0; i < 9; ++i)
            row[CT_IMU_PHI + i] = phi[i];
    Py_RETURN_NONE;
}

static PyMethodDef FusRow_methods[] = {
    {"store", (PyCFunction)(void (*)(void))FusRow_store, METH_FASTCALL,
     "store(k, f (3), w (3), fsrc (3), Phi): IMU ring row k (Phi kept for a moving source)"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(FusRow, "FusRow", "FusRow(idv, cap, moving): InertialPrediction.push's row writer")

/* -------------------------------------------------------------- FusOutput */
typedef struct {
    PyObject_HEAD
    int n, icap, hcap, ocap, moving;
    long long stale_us, dr_after_us, dr_limit_us;
    const double *P, *Th, *idv, *hd;
    double *od;
    int64_t *ot, *ohc;              /* the output ring's times and head / count (KernelRing), or NULL */
    fus_views views;
} FusOutputObject;

FUS_DEALLOC(FusOutput)

static int FusOutput_init(FusOutputObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "P", "Th", "idv", "icap", "hd", "hcap", "od", "ocap", "moving", "stale_us",
                             "dr_after_us", "dr_limit_us", "ot", "ohc", NULL};
    PyObject *o[5], *ot = NULL, *ohc = NULL;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOiOiOipLLL|OO", kwlist, &self->n, &o[0], &o[1], &o[2],
                                     &self->icap, &o[3], &self->hcap, &o[4], &self->ocap, &self->moving,
                                     &self->stale_us, &self->dr_after_us, &self->dr_limit_us, &ot, &ohc))
        return -1;
    if (fus_fresh(&self->views, "FusOutput") < 0)
        return -1;
    if (self->n < CT_GYR + 3 || self->n > 256 || self->icap < 2 || self->hcap < 2 || self->ocap < 2) {
        PyErr_SetString(PyExc_ValueError, "FusOutput: bad state size or ring capacity");
        return -1;
    }
    if (!(self->P = fus_bind(&self->views, o[0], (Py_ssize_t)self->n * self->n, 'd', 0, "P")) ||
        !(self->Th = fus_bind(&self->views, o[1], 9, 'd', 0, "Th")) ||
        !(self->idv = fus_bind(&self->views, o[2], (Py_ssize_t)self->icap * CT_IMU_WIDTH, 'd', 0, "idv")) ||
        !(self->hd = fus_bind(&self->views, o[3], (Py_ssize_t)self->hcap * CT_HIST_WIDTH, 'd', 0, "hd")) ||
        !(self->od = fus_bind(&self->views, o[4], (Py_ssize_t)self->ocap * CT_OUT_WIDTH, 'd', 1, "od"))) {
        fus_release(&self->views);
        return -1;
    }
    self->ot = self->ohc = NULL;
    if (ot != NULL && ohc != NULL &&
        (!(self->ot = fus_bind(&self->views, ot, self->ocap, 'q', 0, "ot")) ||
         !(self->ohc = fus_bind(&self->views, ohc, 2, 'q', 1, "ohc")))) {
        fus_release(&self->views);
        return -1;
    }
    return 0;
}

/* queue(slot, h, k, age, recovering, inconsistent) */
static PyObject *FusOutput_queue(FusOutputObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int slot, h, k, rec, inc, status;
    long long age;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusOutput: not bound");
        return NULL;
    }
    if (fus_nargs("queue", nargs, 6) < 0 || fus_slot(args[0], self->ocap, &slot, "queue") < 0 ||
        fus_slot(args[1], self->hcap, &h, "queue") < 0 || fus_slot(args[2], self->icap, &k, "queue") < 0 ||
        fus_long(args[3], &age) < 0)
        return NULL;
    rec = PyObject_IsTrue(args[4]);
    inc = PyObject_IsTrue(args[5]);
    if (rec < 0 || inc < 0)
        return NULL;
    status = ct_fus_status((int64_t)age, (int64_t)self->stale_us, (int64_t)self->dr_after_us,
                           (int64_t)self->dr_limit_us, rec, inc);
    ct_fus_output(self->od + (long)slot * CT_OUT_WIDTH, self->hd + (long)h * CT_HIST_WIDTH, self->P, self->n,
                  self->Th, self->idv + (long)k * CT_IMU_WIDTH, self->moving, (double)status);
    Py_RETURN_NONE;
}

/* n floats from od into the list l (its first n items) */
static int fus_fill_list(PyObject *l, const double *od, int n, const char *what)
{
    int i;
    if (!PyList_Check(l) || PyList_GET_SIZE(l) < n) {
        PyErr_Format(PyExc_TypeError, "report: %s needs a list of at least %d items", what, n);
        return -1;
    }
    for (i = 0; i < n; ++i) {
        PyObject *x = PyFloat_FromDouble(od[i]);
        if (x == NULL)
            return -1;
        PyList_SetItem(l, i, x);            /* steals x, releases the old item */
    }
    return 0;
}

/* report(slot, p, q, var) -> status: output row slot into the lists p (3), q (4), var (6) */
static PyObject *FusOutput_report(FusOutputObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    const double *od;
    int slot;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusOutput: not bound");
        return NULL;
    }
    if (fus_nargs("report", nargs, 4) < 0 || fus_slot(args[0], self->ocap, &slot, "report") < 0)
        return NULL;
    od = self->od + (long)slot * CT_OUT_WIDTH;
    if (fus_fill_list(args[1], od + CT_OUT_P, 3, "p") < 0 || fus_fill_list(args[2], od + CT_OUT_Q, 4, "q") < 0 ||
        fus_fill_list(args[3], od + CT_OUT_VAR_P, 6, "var") < 0)
        return NULL;
    return PyLong_FromLong((long)od[CT_OUT_STATUS]);
}


/* pose_frame(slot, t_us, seq, src, node, status, quality, range_m) -> bytes or None: the POSE frame
 * (ct_pose_frame) of output row slot sent with `status` when the row carries no OUT_* bit and its
 * position lies within range_m of the source (track.magnetic.in_range3); None for any other row or a
 * value the wire format refuses (the caller sends it through the reference path) */
static PyObject *fus_row_frame(FusOutputObject *self, int slot, long long t, long long seq, long long src,
                               long long node, long long status, long long quality, double range)
{
    uint8_t out[CT_POSE_FRAME_MAX];
    const double *od = self->od + (long)slot * CT_OUT_WIDTH;
    int k;
    if (od[CT_OUT_STATUS] != 0.0 || t < 0 ||
        !(sqrt(od[CT_OUT_P] * od[CT_OUT_P] + od[CT_OUT_P + 1] * od[CT_OUT_P + 1] + od[CT_OUT_P + 2] * od[CT_OUT_P + 2])
          <= range))
        Py_RETURN_NONE;
    k = ct_pose_frame(out, (int)seq, (int)src, (int64_t)node, (uint64_t)t, od + CT_OUT_P, (int64_t)status,
                      (int64_t)quality);
    if (k < 0)
        Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, k);
}

static PyObject *FusOutput_pose_frame(FusOutputObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long t, seq, src, node, status, quality;
    double range;
    int slot;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "FusOutput: not bound");
        return NULL;
    }
    if (fus_nargs("pose_frame", nargs, 8) < 0 || fus_slot(args[0], self->ocap, &slot, "pose_frame") < 0 ||
        fus_long(args[1], &t) < 0 || fus_long(args[2], &seq) < 0 || fus_long(args[3], &src) < 0 ||
        fus_long(args[4], &node) < 0 || fus_long(args[5], &status) < 0 || fus_long(args[6], &quality) < 0 ||
        fus_double(args[7], &range) < 0)
        return NULL;
    return fus_row_frame(self, slot, t, seq, src, node, status, quality, range);
}

/* pose_next(seq, src, node, status, quality, range_m) -> bytes, None or 0: pose_frame of the oldest
 * queued row of the bound output ring, which is then off the queue (bytes); None: that row needs
 * the reference path (left queued); 0: none queued */
static PyObject *FusOutput_pose_next(FusOutputObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long seq, src, node, status, quality;
    double range;
    PyObject *fr;
    int64_t p;
    if (self->ohc == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusOutput: no output ring bound (ot, ohc)");
        return NULL;
    }
    if (fus_nargs("pose_next", nargs, 6) < 0 || fus_long(args[0], &seq) < 0 || fus_long(args[1], &src) < 0 ||
        fus_long(args[2], &node) < 0 || fus_long(args[3], &status) < 0 || fus_long(args[4], &quality) < 0 ||
        fus_double(args[5], &range) < 0)
        return NULL;
    if (self->ohc[1] <= 0)
        return PyLong_FromLong(0);
    p = self->ohc[0] - self->ohc[1];
    if (p < 0)
        p += self->ocap;
    fr = fus_row_frame(self, (int)p, (long long)self->ot[p], seq, src, node, status, quality, range);
    if (fr != NULL && fr != Py_None)
        ct_ring_pop(self->ohc, self->ocap);
    return fr;
}

/* send(seq, src, node, status, quality, range_m, write) -> (sent << 32) + (errors << 1) + ref: pose_next's
 * frames, oldest first, each written through write(frame) (the port's: an exception it raises is
 * cleared and counted in errors, the row off the queue all the same, as Transmitter._fused_pose_compiled
 * counts a tx error), numbered seq, seq + 1, ... (mod 256); it stops when none is queued (ref 0) or at a
 * row that needs the reference path (ref 1, left queued) */
static PyObject *FusOutput_send(FusOutputObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long seq, src, node, status, quality, sent = 0, errors = 0;
    double range;
    PyObject *fr, *write, *res;
    int64_t p;
    if (self->ohc == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusOutput: no output ring bound (ot, ohc)");
        return NULL;
    }
    if (fus_nargs("send", nargs, 7) < 0 || fus_long(args[0], &seq) < 0 || fus_long(args[1], &src) < 0 ||
        fus_long(args[2], &node) < 0 || fus_long(args[3], &status) < 0 || fus_long(args[4], &quality) < 0 ||
        fus_double(args[5], &range) < 0)
        return NULL;
    write = args[6];
    while (self->ohc[1] > 0) {
        p = self->ohc[0] - self->ohc[1];
        if (p < 0)
            p += self->ocap;
        fr = fus_row_frame(self, (int)p, (long long)self->ot[p], (seq + sent) & 0xFF, src, node, status, quality,
                           range);
        if (fr == NULL)
            return NULL;
        if (fr == Py_None) {
            Py_DECREF(fr);
            return PyLong_FromLongLong((sent << 32) + (errors << 1) + 1);
        }
        ct_ring_pop(self->ohc, self->ocap);
        ++sent;
        res = PyObject_CallOneArg(write, fr);
        Py_DECREF(fr);
        if (res == NULL) {
            if (!PyErr_ExceptionMatches(PyExc_Exception))
                return NULL;            /* (KeyboardInterrupt, SystemExit: not a link's failure) */
            PyErr_Clear();
            ++errors;
        } else {
            Py_DECREF(res);
        }
    }
    return PyLong_FromLongLong((sent << 32) + (errors << 1));
}

static PyMethodDef FusOutput_methods[] = {
    {"send", (PyCFunction)(void (*)(void))FusOutput_send, METH_FASTCALL,
     "send(seq, src, node, status, quality, range_m, write) -> (sent << 32) + (errors << 1) + ref: pose_next's "
     "frames written through write, numbered from seq, until none is queued or a row needs the reference path "
     "(ref)"},
    {"pose_next", (PyCFunction)(void (*)(void))FusOutput_pose_next, METH_FASTCALL,
     "pose_next(seq, src, node, status, quality, range_m) -> bytes (sent: off the queue), None (the reference "
     "path's) or 0 (none queued): pose_frame of the oldest queued row"},
    {"pose_frame", (PyCFunction)(void (*)(void))FusOutput_pose_frame, METH_FASTCALL,
     "pose_frame(slot, t_us, seq, src, node, status, quality, range_m) -> bytes or None: the POSE frame of an "
     "output row without OUT_* bits within range_m (None: the reference path sends it)"},
    {"report", (PyCFunction)(void (*)(void))FusOutput_report, METH_FASTCALL,
     "report(slot, p, q, var) -> status: PoseOutput.into_report's copy of output row slot"},
    {"queue", (PyCFunction)(void (*)(void))FusOutput_queue, METH_FASTCALL,
     "queue(slot, h, k, age, recovering, inconsistent): PoseOutput.queue's output row"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(FusOutput, "FusOutput", "FusOutput(n, P, Th, idv, icap, hd, hcap, od, ocap, moving, stale_us, "
         "dr_after_us, dr_limit_us): the fused output rows bound to the live state and history")

/* ---------------------------------------------------------------- FusLive */
/* The forward path of one IMU sample on the live state in one call: FusRow.store, FusPred.advance
 * (ct_fus_propagate, ct_fus_to_source into the live history FusOutput is bound to) and
 * FusOutput.queue, the same kernels in the same order (magnetic_inertial.FusionFilter.push_imu's
 * step not split by a snapshot). */
typedef struct {
    PyObject_HEAD
    FusPredObject *pred;
    FusRowObject *row;
    FusOutputObject *out;
    double *hd;                     /* the live history's rows, writable (out->hd) */
    fus_views views;
} FusLiveObject;

static void FusLive_dealloc(FusLiveObject *self)
{
    Py_XDECREF(self->pred);
    Py_XDECREF(self->row);
    Py_XDECREF(self->out);
    fus_release(&self->views);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int FusLive_init(FusLiveObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"pred", "row", "out", "hd", NULL};
    FusPredObject *pred;
    FusRowObject *row;
    FusOutputObject *out;
    PyObject *hd;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!O!O!O", kwlist, &FusPredType, &pred, &FusRowType, &row,
                                     &FusOutputType, &out, &hd))
        return -1;
    if (self->pred != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusLive: already bound");
        return -1;
    }
    if (!pred->views.n || !row->views.n || !out->views.n) {
        PyErr_SetString(PyExc_ValueError, "FusLive: pred, row and out must be bound");
        return -1;
    }
    if (row->idv != pred->f.idv || out->idv != pred->f.idv || row->cap != pred->f.icap || out->icap != pred->f.icap ||
        out->P != pred->f.ins.P || out->Th != pred->f.ins.Th || out->n != pred->f.ins.n ||
        row->moving != pred->moving || out->moving != pred->moving) {
        PyErr_SetString(PyExc_ValueError, "FusLive: pred, row and out must share the IMU ring, the state and the frame");
        return -1;
    }
    if (!(self->hd = fus_bind(&self->views, hd, (Py_ssize_t)out->hcap * CT_HIST_WIDTH, 'd', 1, "hd")))
        return -1;
    if (self->hd != out->hd) {
        fus_release(&self->views);
        PyErr_SetString(PyExc_ValueError, "FusLive: hd must be the history rows out is bound to");
        return -1;
    }
    Py_INCREF(pred);
    Py_INCREF(row);
    Py_INCREF(out);
    self->pred = pred;
    self->row = row;
    self->out = out;
    return 0;
}

/* FusLive.sample's work once its arguments are read: IMU ring row k := (f, w, fsrc, Phi), the step
 * over [t0, t1] (nring entries held), history row h, and output row o when o >= 0 */
static void fus_live_step(FusLiveObject *self, int k, int nring, int64_t t0, int64_t t1, int h, int o, int64_t age,
                          int rec, int inc, const double *v, const double *phi, double *sym)
{
    FusPredObject *pr = self->pred;
    FusOutputObject *out = self->out;
    double *row, *hd;
    int i;
    row = self->row->idv + (long)k * CT_IMU_WIDTH;                   /* FusRow.store */
    for (i = 0; i < 9; ++i)
        row[CT_IMU_F + i] = v[i];
    if (pr->moving)
        for (i = 0; i < 9; ++i)
            row[CT_IMU_PHI + i] = phi[i];
    ct_fus_propagate(&pr->f, k, nring, t0, t1);  /* FusPred.advance */
    if (sym != NULL)                             /* CovariancePredict.after_predict's symmetrisation */
        ct_symmetrize(pr->f.ins.n, pr->f.ins.P, sym);
    hd = self->hd + (long)h * CT_HIST_WIDTH;
    ct_fus_to_source(row, pr->moving, pr->f.ins.p, pr->f.ins.Th, hd);
    if (o >= 0)                                                     /* FusOutput.queue */
        ct_fus_output(out->od + (long)o * CT_OUT_WIDTH, hd, out->P, out->n, out->Th, row, out->moving,
                      (double)ct_fus_status(age, (int64_t)out->stale_us, (int64_t)out->dr_after_us,
                                            (int64_t)out->dr_limit_us, rec, inc));
}

/* sample(k, nring, t0, t1, h, o, age, recovering, inconsistent, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi):
 * IMU ring row k := the sample (FusRow.store), the live state stepped over [t0, t1]
 * (ct_fus_propagate), history row h := its pose in the source frame (ct_fus_to_source), and, when
 * o >= 0, output row o := the fused pose with its variances and status (FusOutput.queue) */
static PyObject *FusLive_sample(FusLiveObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    FusPredObject *pr = self->pred;
    FusOutputObject *out = self->out;
    double v[9], phi[9];
    long long nring, t0, t1, o, age;
    int k, h, i, rec, inc;
    if (pr == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusLive: not bound");
        return NULL;
    }
    if (fus_nargs("sample", nargs, 19) < 0 || fus_slot(args[0], pr->f.icap, &k, "sample") < 0 ||
        fus_long(args[1], &nring) < 0 || fus_long(args[2], &t0) < 0 || fus_long(args[3], &t1) < 0 ||
        fus_slot(args[4], out->hcap, &h, "sample") < 0 || fus_long(args[5], &o) < 0 || fus_long(args[6], &age) < 0)
        return NULL;
    if (o < -1 || o >= out->ocap) {
        PyErr_Format(PyExc_IndexError, "sample: output slot %lld outside -1..%d", o, out->ocap - 1);
        return NULL;
    }
    if ((rec = PyObject_IsTrue(args[7])) < 0 || (inc = PyObject_IsTrue(args[8])) < 0)
        return NULL;
    for (i = 0; i < 9; ++i)
        if (fus_double(args[9 + i], &v[i]) < 0)
            return NULL;
    if (pr->moving && fus_matrix3(args[18], phi) < 0)
        return NULL;
    fus_live_step(self, k, (int)nring, (int64_t)t0, (int64_t)t1, h, (int)o, (int64_t)age, rec, inc, v, phi, NULL);
    Py_RETURN_NONE;
}

static PyMethodDef FusLive_methods[] = {
    {"sample", (PyCFunction)(void (*)(void))FusLive_sample, METH_FASTCALL,
     "sample(k, nring, t0, t1, h, o, age, recovering, inconsistent, f (3), w (3), fsrc (3), Phi): "
     "FusRow.store, FusPred.advance and (o >= 0) FusOutput.queue in one call"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FusLiveType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FusLive",
    .tp_basicsize = sizeof(FusLiveObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FusLive(pred, row, out, hd): one IMU sample's forward step on the live state (row, step, history, "
              "output) through the bound FusPred, FusRow and FusOutput",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FusLive_init,
    .tp_dealloc = (destructor)FusLive_dealloc,
    .tp_methods = FusLive_methods,
};

/* ---------------------------------------------------------------- OriPred */
typedef struct {
    PyObject_HEAD
    struct ct_ori_pred o;
    double E[9];
    fus_views views;
} OriPredObject;

FUS_DEALLOC(OriPred)

static int OriPred_init(OriPredObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"R", "bias", "dist", "acc", "st", "dist_corr", "acc_corr_time_s", NULL};
    PyObject *o[5];
    struct ct_ori_pred *p = &self->o;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOdd", kwlist, &o[0], &o[1], &o[2], &o[3], &o[4], &p->dist_corr,
                                     &p->acc_corr_time_s))
        return -1;
    if (fus_fresh(&self->views, "OriPred") < 0)
        return -1;
    if (!(p->R = fus_bind(&self->views, o[0], 9, 'd', 1, "R")) ||
        !(p->bias = fus_bind(&self->views, o[1], 3, 'd', 0, "bias")) ||
        !(p->dist = fus_bind(&self->views, o[2], 3, 'd', 1, "dist")) ||
        !(p->acc = fus_bind(&self->views, o[3], 3, 'd', 1, "acc")) ||
        !(p->st = fus_bind(&self->views, o[4], CT_OA_N, 'd', 1, "st"))) {
        fus_release(&self->views);
        return -1;
    }
    p->E = self->E;
    return 0;
}

/* predict(dt, wx, wy, wz, qwd) */
static PyObject *OriPred_predict(OriPredObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[5];
    int i;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "OriPred: not bound");
        return NULL;
    }
    if (fus_nargs("predict", nargs, 5) < 0)
        return NULL;
    for (i = 0; i < 5; ++i)
        if (fus_double(args[i], &v[i]) < 0)
            return NULL;
    ct_ori_predict(&self->o, v[0], v[1], v[2], v[3], v[4]);
    Py_RETURN_NONE;
}

static PyMethodDef OriPred_methods[] = {
    {"predict", (PyCFunction)(void (*)(void))OriPred_predict, METH_FASTCALL,
     "predict(dt, wx, wy, wz, qwd): OrientationFilter.predict after its time step"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(OriPred, "OriPred", "OriPred(R, bias, dist, acc, st, dist_corr, acc_corr_time_s): the orientation "
         "filter's per-sample prediction bound to its state")

/* ----------------------------------------------------------------- OriUpd */
typedef struct {
    PyObject_HEAD
    struct ct_ori_meas o;
    double E[9];
    fus_views views;
} OriUpdObject;

FUS_DEALLOC(OriUpd)

static int OriUpd_init(OriUpdObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "theta", "bias", "dist", "R", "Rc", "b", "d", "a", "sums", "iy", "iH", "iR",
                             "idx", "my", "mH", "mR", "mdx", "hg", "cst", "gravity", "freefall_tolerance",
                             "acc_noise", "acc_motion_sigma", "acc_adapt_gain", "mag_noise", "dist_sigma",
                             "dist_norm_gain", "dist_dip_gain", "dist_smoothing", "heading_only", NULL};
    PyObject *v[16];
    struct ct_ori_meas *o = &self->o;
    Py_ssize_t m;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiiiOOOOOOOOOOOOOOOOddddddddddp", kwlist, &o->n, &o->theta,
                                     &o->bias, &o->dist, &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7],
                                     &v[8], &v[9], &v[10], &v[11], &v[12], &v[13], &v[14], &v[15], &o->gravity,
                                     &o->freefall_tolerance, &o->acc_noise, &o->acc_motion_sigma,
                                     &o->acc_adapt_gain, &o->mag_noise, &o->dist_sigma, &o->dist_norm_gain,
                                     &o->dist_dip_gain, &o->dist_smoothing, &o->heading_only))
        return -1;
    if (fus_fresh(&self->views, "OriUpd") < 0)
        return -1;
    if (o->n < 9 || o->n > 256 || o->theta < 0 || o->bias < 0 || o->dist < 0 || o->theta + 3 > o->n ||
        o->bias + 3 > o->n || o->dist + 3 > o->n) {
        PyErr_SetString(PyExc_ValueError, "OriUpd: bad state size or row indices");
        return -1;
    }
    m = (Py_ssize_t)3 * o->n;
    if (!(o->R = fus_bind(&self->views, v[0], 9, 'd', 1, "R")) ||
        !(o->Rc = fus_bind(&self->views, v[1], 9, 'd', 1, "Rc")) ||
        !(o->b = fus_bind(&self->views, v[2], 3, 'd', 1, "b")) ||
        !(o->d = fus_bind(&self->views, v[3], 3, 'd', 1, "d")) ||
        !(o->a = fus_bind(&self->views, v[4], 3, 'd', 1, "a")) ||
        !(o->sums = fus_bind(&self->views, v[5], CT_OA_N, 'd', 0, "sums")) ||
        !(o->iy = fus_bind(&self->views, v[6], 3, 'd', 1, "iy")) ||
        !(o->iH = fus_bind(&self->views, v[7], m, 'd', 1, "iH")) ||
        !(o->iR = fus_bind(&self->views, v[8], 9, 'd', 1, "iR")) ||
        !(o->idx = fus_bind(&self->views, v[9], o->n, 'd', 0, "idx")) ||
        !(o->my = fus_bind(&self->views, v[10], 3, 'd', 1, "my")) ||
        !(o->mH = fus_bind(&self->views, v[11], m, 'd', 1, "mH")) ||
        !(o->mR = fus_bind(&self->views, v[12], 9, 'd', 1, "mR")) ||
        !(o->mdx = fus_bind(&self->views, v[13], o->n, 'd', 0, "mdx")) ||
        !(o->hg = fus_bind(&self->views, v[14], 3, 'd', 0, "hg")) ||
        !(o->cst = fus_bind(&self->views, v[15], CT_CS_N, 'd', 1, "cst"))) {
        fus_release(&self->views);
        return -1;
    }
    o->E = self->E;
    return 0;
}

static int OriUpd_bound(OriUpdObject *self)
{
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "OriUpd: not bound");
        return -1;
    }
    return 0;
}

/* acc_begin(ax, ay, az, motion_ms) -> bool (False: free fall, nothing to update) */
static PyObject *OriUpd_acc_begin(OriUpdObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[4];
    int i;
    if (OriUpd_bound(self) < 0 || fus_nargs("acc_begin", nargs, 4) < 0)
        return NULL;
    for (i = 0; i < 4; ++i)
        if (fus_double(args[i], &v[i]) < 0)
            return NULL;
    if (ct_ori_incl_begin(&self->o, v[0], v[1], v[2], v[3]))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* acc_end(ok): the inclination's correction applied when ok, then the acceleration a+ */
static PyObject *OriUpd_acc_end(OriUpdObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int ok;
    if (OriUpd_bound(self) < 0 || fus_nargs("acc_end", nargs, 1) < 0 || (ok = PyObject_IsTrue(args[0])) < 0)
        return NULL;
    if (ok)
        ct_ori_apply(&self->o, self->o.idx);
    ct_ori_post_acc(&self->o);
    Py_RETURN_NONE;
}

/* mag_fill(mx, my, mz) */
static PyObject *OriUpd_mag_fill(OriUpdObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[3];
    int i;
    if (OriUpd_bound(self) < 0 || fus_nargs("mag_fill", nargs, 3) < 0)
        return NULL;
    for (i = 0; i < 3; ++i)
        if (fus_double(args[i], &v[i]) < 0)
            return NULL;
    ct_ori_compass_fill(&self->o, v[0], v[1], v[2]);
    Py_RETURN_NONE;
}

/* mag_apply(): the compass's correction */
static PyObject *OriUpd_mag_apply(OriUpdObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (OriUpd_bound(self) < 0 || fus_nargs("mag_apply", nargs, 0) < 0)
        return NULL;
    (void)args;
    ct_ori_apply(&self->o, self->o.mdx);
    Py_RETURN_NONE;
}

static PyMethodDef OriUpd_methods[] = {
    {"acc_begin", (PyCFunction)(void (*)(void))OriUpd_acc_begin, METH_FASTCALL,
     "acc_begin(ax, ay, az, motion_ms) -> bool: update_acc's free-fall test and the inclination's y, H, R"},
    {"acc_end", (PyCFunction)(void (*)(void))OriUpd_acc_end, METH_FASTCALL,
     "acc_end(ok): _apply of the inclination's correction when ok, then _post_acc"},
    {"mag_fill", (PyCFunction)(void (*)(void))OriUpd_mag_fill, METH_FASTCALL,
     "mag_fill(mx, my, mz): Compass.update's driving noise and the compass's y, H, R"},
    {"mag_apply", (PyCFunction)(void (*)(void))OriUpd_mag_apply, METH_FASTCALL,
     "mag_apply(): _apply of the compass's correction"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(OriUpd, "OriUpd", "OriUpd(n, theta, bias, dist, R, Rc, b, d, a, sums, iy, iH, iR, idx, my, mH, mR, mdx, "
         "hg, cst, gravity, ..., heading_only): the orientation filter's updates around their Kalman update")

/* ----------------------------------------------------------- QuietSample */
typedef struct {
    PyObject_HEAD
    struct ct_quiet q;
    fus_views views;
} QuietSampleObject;

FUS_DEALLOC(QuietSample)

static int QuietSample_init(QuietSampleObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"t", "flags", "starts", "ends", "before", "after", NULL};
    PyObject *o[4];
    struct ct_quiet *q = &self->q;
    Py_ssize_t cap, n;
    long long before, after;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOLL", kwlist, &o[0], &o[1], &o[2], &o[3], &before, &after))
        return -1;
    if (fus_fresh(&self->views, "QuietSample") < 0)
        return -1;
    if ((cap = PyObject_Length(o[0])) < 0 || (n = PyObject_Length(o[2])) < 0)
        return -1;
    if (cap < 2 || PyObject_Length(o[1]) != cap || PyObject_Length(o[3]) != n) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "QuietSample: t and flags need the ring's length (>= 2), starts "
                            "and ends the schedule's");
        return -1;
    }
    if (!(q->tv = fus_bind(&self->views, o[0], cap, 'q', 0, "t")))
        return -1;
    if (ct_py_buffer(o[1], cap, 1, "B", 0, &self->views.v[self->views.n], "flags") < 0) {
        fus_release(&self->views);
        return -1;
    }
    q->fl = self->views.v[self->views.n++].buf;
    if (!(q->ps = fus_bind(&self->views, o[2], n, 'q', 0, "starts")) ||
        !(q->pe = fus_bind(&self->views, o[3], n, 'q', 0, "ends"))) {
        fus_release(&self->views);
        return -1;
    }
    q->cap = cap;
    q->n = n;
    q->before = before;
    q->after = after;
    return 0;
}

/* find(head, count, after_t, t_imu, max_age_us) -> slot or -1 */
static PyObject *QuietSample_find(QuietSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long v[5];
    int i;
    if (!self->views.n) {
        PyErr_SetString(PyExc_RuntimeError, "QuietSample: not bound");
        return NULL;
    }
    if (fus_nargs("find", nargs, 5) < 0)
        return NULL;
    for (i = 0; i < 5; ++i)
        if (fus_long(args[i], &v[i]) < 0)
            return NULL;
    if (v[0] < 0 || v[0] >= self->q.cap || v[1] < 0 || v[1] > self->q.cap) {
        PyErr_SetString(PyExc_IndexError, "find: head or count outside the ring");
        return NULL;
    }
    return PyLong_FromLongLong((long long)ct_quiet_sample(&self->q, v[0], v[1], v[2], v[3], v[4]));
}

static PyMethodDef QuietSample_methods[] = {
    {"find", (PyCFunction)(void (*)(void))QuietSample_find, METH_FASTCALL,
     "find(head, count, after_t, t_imu, max_age_us) -> slot or -1: track.burst_fusion.quiet_sample"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(QuietSample, "QuietSample", "QuietSample(t, flags, starts, ends, before, after): the compass sample "
         "search (quiet_sample) bound to a magnetometer ring and a pulse schedule")


/* ---------------------------------------------------------------- OriStep */
#define OS_MAXBUF 64

typedef struct {
    PyObject_HEAD
    struct ct_ori_step o;
    double E[9];
    Py_buffer v[OS_MAXBUF];
    int nv;
} OriStepObject;

static void OriStep_release(OriStepObject *self)
{
    while (self->nv > 0)
        PyBuffer_Release(&self->v[--self->nv]);
}

static void OriStep_dealloc(OriStepObject *self)
{
    OriStep_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* bind obj (or its attribute `attr` when attr is not NULL) as `count` items of `fmt` */
static void *os_bind(OriStepObject *self, PyObject *obj, const char *attr, Py_ssize_t count, const char *fmt,
                     Py_ssize_t itemsize, int writable)
{
    PyObject *a = obj;
    int rc;
    if (self->nv >= OS_MAXBUF) {
        PyErr_SetString(PyExc_RuntimeError, "OriStep: too many buffers");
        return NULL;
    }
    if (attr != NULL && (a = PyObject_GetAttrString(obj, attr)) == NULL)
        return NULL;
    rc = ct_py_buffer(a, count, itemsize, fmt, writable, &self->v[self->nv], attr != NULL ? attr : "buffer");
    if (attr != NULL)
        Py_DECREF(a);
    if (rc < 0)
        return NULL;
    return self->v[self->nv++].buf;
}

#define OS_D(obj, attr, count, wr) ((double *)os_bind(self, (obj), (attr), (count), "d", 8, (wr)))

/* a float attribute */
static int os_attr_double(PyObject *obj, const char *attr, double *x)
{
    PyObject *a = PyObject_GetAttrString(obj, attr);
    int rc;
    if (a == NULL)
        return -1;
    rc = ct_py_double(a, x);
    Py_DECREF(a);
    return rc;
}

/* the buffers of one ekf.KalmanUpdate (3 x n) into u, its NIS cell into *nis */
static int os_bind_kalman(OriStepObject *self, PyObject *upd, int n, struct ct_kalman *u, double **nis)
{
    Py_ssize_t m = 3, mn = 3 * (Py_ssize_t)n, nn = (Py_ssize_t)n * n;
    u->n = n;
    u->m = 3;
    if (!(u->H = OS_D(upd, "H", mn, 1)) || !(u->R = OS_D(upd, "R", m * m, 1)) || !(u->y = OS_D(upd, "y", m, 1)) ||
        !(u->dx = OS_D(upd, "dx", n, 1)) || !(u->S = OS_D(upd, "S", m * m, 1)) ||
        !(u->Sinv = OS_D(upd, "Sinv", m * m, 1)) || !(u->K = OS_D(upd, "K", mn, 1)) ||
        !(u->PHt = OS_D(upd, "_PHt", mn, 1)) || !(u->T = OS_D(upd, "_T", nn, 1)) ||
        !(u->TH = OS_D(upd, "_TH", mn, 1)) || !(u->X = OS_D(upd, "_X", nn, 1)) ||
        !(u->KR = OS_D(upd, "_KR", mn, 1)) || !(u->w = OS_D(upd, "_w", m, 1)) || !(u->L = OS_D(upd, "_L", m * m, 1)) ||
        !(u->M = OS_D(upd, "_M", m * m, 1)) || !(*nis = OS_D(upd, "_nis", 1, 1)))
        return -1;
    return 0;
}

/* OriStep(f, upd_acc, upd_mag, compass, flip_s, flip_i, inc, ct, mag_t, mag_flags, mag_b, starts, ends,
 *         before, after, every, max_age_us, symmetrize_every, flip_gain, n, theta, bias, dist) */
static int OriStep_init(OriStepObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"f", "upd_acc", "upd_mag", "compass", "flip_s", "flip_i", "inc", "ct", "mag_t",
                             "mag_flags", "mag_b", "starts", "ends", "before", "after", "every", "max_age_us",
                             "symmetrize_every", "flip_gain", "n", "theta", "bias", "dist", NULL};
    PyObject *f, *iu, *mu, *cp, *fs, *fi, *inc, *ct, *mt, *mf, *mb, *ps, *pe, *prm = NULL, *pred = NULL;
    long long before, after, max_age;
    int every, sym, n, th, bi, di, heading = 0;
    double gain;
    Py_ssize_t cap, np_, nn;
    struct ct_ori_step *o = &self->o;
    struct ct_ori_meas *me = &o->meas;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOOOOOOOLLiLidiiii", kwlist, &f, &iu, &mu, &cp, &fs, &fi, &inc,
                                     &ct, &mt, &mf, &mb, &ps, &pe, &before, &after, &every, &max_age, &sym, &gain,
                                     &n, &th, &bi, &di))
        return -1;
    if (self->nv) {
        PyErr_SetString(PyExc_RuntimeError, "OriStep: already bound");
        return -1;
    }
    if (n < 9 || n > 256 || th < 0 || bi < 0 || di < 0 || th + 3 > n || bi + 3 > n || di + 3 > n || every < 1 ||
        sym < 1) {
        PyErr_SetString(PyExc_ValueError, "OriStep: bad state size, row indices, update interval or symmetrisation");
        return -1;
    }
    nn = (Py_ssize_t)n * n;
    if ((cap = PyObject_Length(mt)) < 2 || (np_ = PyObject_Length(ps)) < 0 || PyObject_Length(pe) != np_) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "OriStep: the magnetometer ring needs >= 2 slots, starts and ends "
                            "the schedule's length");
        return -1;
    }
    if ((prm = PyObject_GetAttrString(f, "prm")) == NULL || (pred = PyObject_GetAttrString(f, "pred")) == NULL)
        goto fail;
    /* OrientationFilter.predict (ct_ori_pred) */
    if (!(o->pred.R = OS_D(f, "R", 9, 1)) || !(o->pred.bias = OS_D(f, "bias", 3, 1)) ||
        !(o->pred.dist = OS_D(f, "dist", 3, 1)) || !(o->pred.acc = OS_D(f, "acc", 3, 1)) ||
        !(o->pred.st = OS_D(f, "sums", CT_OA_N, 1)) || os_attr_double(prm, "dist_corr", &o->pred.dist_corr) < 0 ||
        os_attr_double(prm, "acc_corr_time_s", &o->pred.acc_corr_time_s) < 0)
        goto fail;
    o->pred.E = self->E;
    /* propagate (ct_ori) */
    o->prop.n = n;
    o->prop.theta = th;
    o->prop.bias = bi;
    o->prop.dist = di;
    o->prop.R = o->pred.R;
    if (!(o->prop.Rc = OS_D(f, "_Rc", 9, 1)) || !(o->prop.A = OS_D(pred, "A", nn, 1)) ||
        !(o->prop.Q = OS_D(pred, "Q", nn, 1)) || !(o->prop.P = OS_D(f, "P", nn, 1)) ||
        !(o->prop.T = OS_D(pred, "_T", nn, 1)) || os_attr_double(prm, "gyro_noise", &o->prop.gyro_noise) < 0 ||
        os_attr_double(prm, "gyro_bias_rw", &o->prop.gyro_bias_rw) < 0)
        goto fail;
    /* the two updates */
    if (os_bind_kalman(self, iu, n, &o->iu, &o->inis) < 0 || os_bind_kalman(self, mu, n, &o->mu, &o->mnis) < 0 ||
        os_attr_double(iu, "gate", &o->igate) < 0 || os_attr_double(mu, "gate", &o->mgate) < 0)
        goto fail;
    /* their measurements (ct_ori_meas) */
    me->n = n;
    me->theta = th;
    me->bias = bi;
    me->dist = di;
    me->R = o->pred.R;
    me->Rc = o->prop.Rc;
    me->b = o->pred.bias;
    me->d = o->pred.dist;
    me->a = o->pred.acc;
    me->E = self->E;
    me->sums = o->pred.st;
    me->iy = (double *)o->iu.y;
    me->iH = (double *)o->iu.H;
    me->iR = (double *)o->iu.R;
    me->idx = o->iu.dx;
    me->my = (double *)o->mu.y;
    me->mH = (double *)o->mu.H;
    me->mR = (double *)o->mu.R;
    me->mdx = o->mu.dx;
    if (!(me->hg = OS_D(cp, "h_g", 3, 0)) || !(me->cst = OS_D(cp, "state", CT_CS_N, 1)) ||
        os_attr_double(prm, "gravity", &me->gravity) < 0 ||
        os_attr_double(prm, "freefall_tolerance", &me->freefall_tolerance) < 0 ||
        os_attr_double(prm, "acc_noise", &me->acc_noise) < 0 ||
        os_attr_double(prm, "acc_motion_sigma", &me->acc_motion_sigma) < 0 ||
        os_attr_double(prm, "acc_adapt_gain", &me->acc_adapt_gain) < 0 ||
        os_attr_double(prm, "mag_noise", &me->mag_noise) < 0 ||
        os_attr_double(prm, "dist_sigma", &me->dist_sigma) < 0 ||
        os_attr_double(prm, "dist_norm_gain", &me->dist_norm_gain) < 0 ||
        os_attr_double(prm, "dist_dip_gain", &me->dist_dip_gain) < 0 ||
        os_attr_double(prm, "dist_smoothing", &me->dist_smoothing) < 0 ||
        os_attr_double(prm, "acc_adapt_tau_s", &o->acc_adapt_tau_s) < 0)
        goto fail;
    {
        PyObject *h = PyObject_GetAttrString(prm, "compass_heading_only");
        if (h == NULL || (heading = PyObject_IsTrue(h)) < 0) {
            Py_XDECREF(h);
            goto fail;
        }
        Py_DECREF(h);
        me->heading_only = heading;
    }
    /* the compass sample's search, the ring's fields, FlipOffset, Inclination, _Ori */
    if (!(o->q.tv = (const int64_t *)os_bind(self, mt, NULL, cap, "ql", 8, 0)) ||
        !(o->q.fl = (const uint8_t *)os_bind(self, mf, NULL, cap, "B", 1, 0)) ||
        !(o->q.ps = (const int64_t *)os_bind(self, ps, NULL, np_, "ql", 8, 0)) ||
        !(o->q.pe = (const int64_t *)os_bind(self, pe, NULL, np_, "ql", 8, 0)) ||
        !(o->mb = OS_D(mb, NULL, 3 * cap, 0)) || !(o->fl = OS_D(fs, NULL, CT_FL_N, 1)) ||
        !(o->fi = (int64_t *)os_bind(self, fi, NULL, CT_FI_COUNT, "ql", 8, 1)) ||
        !(o->inc = OS_D(inc, NULL, CT_IN_N, 1)) || !(o->ct = (int64_t *)os_bind(self, ct, NULL, 1, "ql", 8, 1)))
        goto fail;
    o->q.cap = cap;
    o->q.n = np_;
    o->q.before = before;
    o->q.after = after;
    o->flip_gain = gain;
    o->every = every;
    o->symmetrize_every = sym;
    o->max_age_us = max_age;
    Py_DECREF(prm);
    Py_DECREF(pred);
    return 0;
fail:
    Py_XDECREF(prm);
    Py_XDECREF(pred);
    OriStep_release(self);
    return -1;
}

/* sample(t, ax, ay, az, wx, wy, wz, t_prev, n, head, count, pcount, icount, mcount) -> CT_OS_* bits */
static PyObject *OriStep_sample(OriStepObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double v[6];
    long long t, tp, n, head, count, pc, ic, mc;
    int i;
    if (!self->nv) {
        PyErr_SetString(PyExc_RuntimeError, "OriStep: not bound");
        return NULL;
    }
    if (fus_nargs("sample", nargs, 14) < 0 || fus_long(args[0], &t) < 0)
        return NULL;
    for (i = 0; i < 6; ++i)
        if (fus_double(args[1 + i], &v[i]) < 0)
            return NULL;
    if (fus_long(args[7], &tp) < 0 || fus_long(args[8], &n) < 0 || fus_long(args[9], &head) < 0 ||
        fus_long(args[10], &count) < 0 || fus_long(args[11], &pc) < 0 || fus_long(args[12], &ic) < 0 ||
        fus_long(args[13], &mc) < 0)
        return NULL;
    if (head < 0 || head >= self->o.q.cap || count < 0 || count > self->o.q.cap) {
        PyErr_SetString(PyExc_IndexError, "sample: head or count outside the magnetometer ring");
        return NULL;
    }
    return PyLong_FromLong(ct_ori_sample(&self->o, (int64_t)t, v[0], v[1], v[2], v[3], v[4], v[5], (int64_t)tp,
                                         (int)n, (int64_t)head, (int64_t)count, (int64_t)pc, (int64_t)ic,
                                         (int64_t)mc));
}

static PyMethodDef OriStep_methods[] = {
    {"sample", (PyCFunction)(void (*)(void))OriStep_sample, METH_FASTCALL,
     "sample(t, ax, ay, az, wx, wy, wz, t_prev, n, head, count, pcount, icount, mcount) -> bits: one IMU sample "
     "of _Ori.step on an initialised filter that has learned its compass"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject OriStepType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.OriStep",
    .tp_basicsize = sizeof(OriStepObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "OriStep(f, upd_acc, upd_mag, compass, flip_s, flip_i, inc, ct, mag_t, mag_flags, mag_b, starts, ends, "
              "before, after, every, max_age_us, symmetrize_every, flip_gain, n, theta, bias, dist): an orientation "
              "filter's IMU sample (compass search, set/reset offset, prediction, updates) in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)OriStep_init,
    .tp_dealloc = (destructor)OriStep_dealloc,
    .tp_methods = OriStep_methods,
};


/* --------------------------------------------------------------- ImuSample */
/* One IMU sample of a sensor of a fused tracker in one call (track.burst_fusion.SensorInertial
 * .process on a sample both parts take whole): the sample off the sensor's IMU ring, the orientation
 * filter's step (OriStep, ct_ori_sample), and the fusion filter's forward step (FusLive) with the
 * sample kept in its IMU ring, the pose in the live history and the fused pose queued; the rings'
 * heads and counts in their int64 arrays (fusion_rings.KernelRing), the latest bias-free rate into
 * w_last. */
typedef struct {
    PyObject_HEAD
    OriStepObject *ori;
    FusLiveObject *live;
    int64_t *in_hc, *in_t, *pi_hc, *pi_t, *hi_hc, *hi_t, *ou_hc, *ou_t;
    const double *in_d;
    double *wl;
    double *sym;                    /* n x n: the symmetrisation's scratch (CovariancePredict._T2) */
    int sym_every;                  /* ekf.SYMMETRIZE_EVERY */
    int64_t in_cap, pi_cap, hi_cap, ou_cap;
    int64_t held_t;                 /* begin's sample (its time, f, w) and compass sample, for finish */
    double held[6], held_m[CT_OM_N];
    int holding;
    fus_views views;
    /* bind_state's: the owners' per-sample state, the source's r* (3) and Phi (9) */
    struct ct_sample_state ss;
    const double *fref, *phi;
    int stated;
    fus_views sviews;
    /* bind_split's: the live state's Replay (its step split at a snapshot, the snapshot taken: py_fusion.h),
     * or NULL (a sample with a snapshot inside its step is handed back); the snapshot's state's time */
    PyObject *replay;
    int64_t *snap_ts;
    fus_views pviews;
} ImuSampleObject;

static void ImuSample_dealloc(ImuSampleObject *self)
{
    Py_XDECREF(self->ori);
    Py_XDECREF(self->live);
    Py_XDECREF(self->replay);
    fus_release(&self->views);
    fus_release(&self->sviews);
    fus_release(&self->pviews);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* a KernelRing's (t, hc) bound; its capacity */
static int imu_ring_bind(ImuSampleObject *self, PyObject *t, PyObject *hc, int64_t **tp, int64_t **hp,
                         int64_t *cap, const char *what)
{
    Py_ssize_t n = PyObject_Length(t);
    if (n < 2) {
        if (!PyErr_Occurred())
            PyErr_Format(PyExc_ValueError, "ImuSample: %s needs at least 2 slots", what);
        return -1;
    }
    if (!(*tp = fus_bind(&self->views, t, n, 'q', 1, what)) || !(*hp = fus_bind(&self->views, hc, 2, 'q', 1, what)))
        return -1;
    *cap = n;
    return 0;
}

static int ImuSample_init(ImuSampleObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"ori", "live", "in_t", "in_d", "in_hc", "pi_t", "pi_hc", "hi_t", "hi_hc", "ou_t",
                             "ou_hc", "w_last", "sym", "symmetrize_every", NULL};
    PyObject *ori, *live, *o[11];
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!O!OOOOOOOOOOOi", kwlist, &OriStepType, &ori, &FusLiveType, &live,
                                     &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10],
                                     &self->sym_every))
        return -1;
    if (self->sym_every < 1) {
        PyErr_SetString(PyExc_ValueError, "ImuSample: symmetrize_every must be >= 1");
        return -1;
    }
    if (fus_fresh(&self->views, "ImuSample") < 0)
        return -1;
    if (((OriStepObject *)ori)->nv == 0 || ((FusLiveObject *)live)->pred == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: OriStep or FusLive not bound");
        return -1;
    }
    if (imu_ring_bind(self, o[0], o[2], &self->in_t, &self->in_hc, &self->in_cap, "in") < 0 ||
        !(self->in_d = fus_bind(&self->views, o[1], self->in_cap * 6, 'd', 0, "in_d")) ||
        imu_ring_bind(self, o[3], o[4], &self->pi_t, &self->pi_hc, &self->pi_cap, "pi") < 0 ||
        imu_ring_bind(self, o[5], o[6], &self->hi_t, &self->hi_hc, &self->hi_cap, "hi") < 0 ||
        imu_ring_bind(self, o[7], o[8], &self->ou_t, &self->ou_hc, &self->ou_cap, "ou") < 0 ||
        !(self->wl = fus_bind(&self->views, o[9], 3, 'd', 1, "w_last")) ||
        !(self->sym = fus_bind(&self->views, o[10],
                               (Py_ssize_t)((FusLiveObject *)live)->pred->f.ins.n * ((FusLiveObject *)live)->pred->f.ins.n,
                               'd', 1, "sym"))) {
        fus_release(&self->views);
        return -1;
    }
    {
        FusLiveObject *lv = (FusLiveObject *)live;
        if (self->pi_cap != lv->pred->f.icap || self->hi_cap != lv->out->hcap || self->ou_cap != lv->out->ocap) {
            fus_release(&self->views);
            PyErr_SetString(PyExc_ValueError, "ImuSample: the rings are not the ones FusLive is bound to");
            return -1;
        }
    }
    Py_INCREF(ori);
    Py_INCREF(live);
    self->ori = (OriStepObject *)ori;
    self->live = (FusLiveObject *)live;
    return 0;
}

/* the fusion filter's arguments of sample and finish: t0, age, recovering, inconsistent, fcount, rx, ry, rz
 * (into v[6..8]), Phi */
static int imu_fus_args(ImuSampleObject *self, PyObject *const *args, long long *t0, long long *age, int *rec,
                        int *inc, long long *fc, double *v, double *phi)
{
    int i;
    if (fus_long(args[0], t0) < 0 || fus_long(args[1], age) < 0 || (*rec = PyObject_IsTrue(args[2])) < 0 ||
        (*inc = PyObject_IsTrue(args[3])) < 0 || fus_long(args[4], fc) < 0)
        return -1;
    for (i = 0; i < 3; ++i)
        if (fus_double(args[5 + i], &v[6 + i]) < 0)
            return -1;
    if (self->live->pred->moving && fus_matrix3(args[8], phi) < 0)
        return -1;
    return 0;
}

/* sample's work on a queue with room and a ring not empty (v[6..8]: r*): the orientation step's bits */
static int imu_sample_whole(ImuSampleObject *self, long long t0, long long age, int rec, int inc, long long fc,
                            double *v, const double *phi, long long tp, long long n, long long head,
                            long long count, long long pc, long long ic, long long mc, long long steps)
{
    const double *d, *b;
    int64_t k, t, kf, h, o;
    int r, i;
    k = ct_ring_pop(self->in_hc, self->in_cap);
    t = self->in_t[k];
    d = self->in_d + 6 * k;
    for (i = 0; i < 6; ++i)
        v[i] = d[i];
    if (steps < 0)
        r = ct_ori_sample(&self->ori->o, t, v[0], v[1], v[2], v[3], v[4], v[5], (int64_t)tp, (int)n, (int64_t)head,
                          (int64_t)count, (int64_t)pc, (int64_t)ic, (int64_t)mc);
    else                                        /* its prediction may orthonormalise R (OrientationFilter.predict) */
        r = ct_ori_sample_ortho(&self->ori->o, t, v[0], v[1], v[2], v[3], v[4], v[5], (int64_t)tp, (int)n,
                                (int64_t)head, (int64_t)count, (int64_t)pc, (int64_t)ic, (int64_t)mc, (int64_t)steps);
    o = ct_ring_push(self->ou_hc, self->ou_cap, self->ou_t, t);          /* PoseOutput's row */
    kf = ct_ring_push(self->pi_hc, self->pi_cap, self->pi_t, t);         /* InertialPrediction.sample */
    h = ct_ring_push(self->hi_hc, self->hi_cap, self->hi_t, t);
    fus_live_step(self->live, (int)kf, (int)self->pi_hc[1], (int64_t)t0, t, (int)h, (int)o, (int64_t)age, rec, inc,
                  v, phi, (fc + 1) % self->sym_every == 0 ? self->sym : NULL);
    b = self->ori->o.pred.bias;                                          /* SensorInertial.w_last */
    self->wl[0] = v[3] - b[0];
    self->wl[1] = v[4] - b[1];
    self->wl[2] = v[5] - b[2];
    return r;
}

/* sample(t0, age, recovering, inconsistent, fcount, rx, ry, rz, Phi, t_prev, n, head, count, pcount, icount,
 *        mcount)
 * -> the orientation step's CT_OS_* bits: the oldest sample of the sensor's IMU ring (its time t)
 * through _Ori.step (OriStep.sample's arguments) and FusionFilter.push_imu's forward step from t0;
 * fcount: the fusion state's prediction count (the step after which P is symmetrised, as
 * CovariancePredict.after_predict does it); -1 (nothing done) when the output queue is full
 * (PoseOutput.queue would drop the pose) */
static PyObject *ImuSample_sample(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long tp, n, head, count, pc, ic, mc, t0, age, fc;
    double v[9], phi[9];
    int rec, inc;
    if (self->ori == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: not bound");
        return NULL;
    }
    if (fus_nargs("sample", nargs, 16) < 0 || imu_fus_args(self, args, &t0, &age, &rec, &inc, &fc, v, phi) < 0 ||
        fus_long(args[9], &tp) < 0 || fus_long(args[10], &n) < 0 || fus_long(args[11], &head) < 0 ||
        fus_long(args[12], &count) < 0 || fus_long(args[13], &pc) < 0 || fus_long(args[14], &ic) < 0 ||
        fus_long(args[15], &mc) < 0)
        return NULL;
    if (head < 0 || head >= self->ori->o.q.cap || count < 0 || count > self->ori->o.q.cap) {
        PyErr_SetString(PyExc_IndexError, "sample: head or count outside the magnetometer ring");
        return NULL;
    }
    if (self->ou_hc[1] == self->ou_cap)                                  /* the output queue is full */
        return PyLong_FromLong(-1);
    if (self->in_hc[1] <= 0) {
        PyErr_SetString(PyExc_IndexError, "sample: the IMU ring is empty");
        return NULL;
    }
    return PyLong_FromLong(imu_sample_whole(self, t0, age, rec, inc, fc, v, phi, tp, n, head, count, pc, ic, mc, -1));
}

/* peek() -> the time of the oldest sample of the IMU ring, or -1 when it is empty */
static PyObject *ImuSample_peek(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t p;
    (void)args;
    if (self->ori == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: not bound");
        return NULL;
    }
    if (fus_nargs("peek", nargs, 0) < 0)
        return NULL;
    if (self->in_hc[1] <= 0)
        return PyLong_FromLong(-1);
    p = self->in_hc[0] - self->in_hc[1];
    if (p < 0)
        p += self->in_cap;
    return PyLong_FromLongLong((long long)self->in_t[p]);
}

/* begin(t_prev, head, count) -> bits or -1: sample's first half for a sample whose prediction the
 * caller follows with the orientation's orthonormalisation: the oldest sample off the IMU ring, the
 * compass sample and the prediction (ct_ori_sample_begin), held for finish; -1 (nothing done) when
 * the output queue is full */
static PyObject *ImuSample_begin(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long tp, head, count;
    const double *d;
    int64_t k;
    int i;
    if (self->ori == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: not bound");
        return NULL;
    }
    if (fus_nargs("begin", nargs, 3) < 0 || fus_long(args[0], &tp) < 0 || fus_long(args[1], &head) < 0 ||
        fus_long(args[2], &count) < 0)
        return NULL;
    if (head < 0 || head >= self->ori->o.q.cap || count < 0 || count > self->ori->o.q.cap) {
        PyErr_SetString(PyExc_IndexError, "begin: head or count outside the magnetometer ring");
        return NULL;
    }
    if (self->ou_hc[1] == self->ou_cap)
        return PyLong_FromLong(-1);
    if ((k = ct_ring_pop(self->in_hc, self->in_cap)) < 0) {
        PyErr_SetString(PyExc_IndexError, "begin: the IMU ring is empty");
        return NULL;
    }
    self->held_t = self->in_t[k];
    d = self->in_d + 6 * k;
    for (i = 0; i < 6; ++i)
        self->held[i] = d[i];
    self->holding = 1;
    return PyLong_FromLong(ct_ori_sample_begin(&self->ori->o, self->held_t, self->held[3], self->held[4],
                                               self->held[5], (int64_t)tp, (int64_t)head, (int64_t)count,
                                               self->held_m));
}

/* finish(t0, age, recovering, inconsistent, fcount, rx, ry, rz, Phi, n, pcount, icount, mcount) -> bits: the
 * held sample's update round (ct_ori_sample_end) and the fusion filter's forward step, as sample */
static PyObject *ImuSample_finish(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long n, pc, ic, mc, t0, age, fc;
    double v[9], phi[9];
    const double *b;
    int64_t t, kf, h, o;
    int r, rec, inc, i;
    if (self->ori == NULL || !self->holding) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: finish without begin");
        return NULL;
    }
    if (fus_nargs("finish", nargs, 13) < 0 || imu_fus_args(self, args, &t0, &age, &rec, &inc, &fc, v, phi) < 0 ||
        fus_long(args[9], &n) < 0 || fus_long(args[10], &pc) < 0 || fus_long(args[11], &ic) < 0 ||
        fus_long(args[12], &mc) < 0)
        return NULL;
    self->holding = 0;
    t = self->held_t;
    for (i = 0; i < 6; ++i)
        v[i] = self->held[i];
    r = ct_ori_sample_end(&self->ori->o, v[0], v[1], v[2], (int)n, self->held_m, (int64_t)pc, (int64_t)ic,
                          (int64_t)mc);
    o = ct_ring_push(self->ou_hc, self->ou_cap, self->ou_t, t);
    kf = ct_ring_push(self->pi_hc, self->pi_cap, self->pi_t, t);
    h = ct_ring_push(self->hi_hc, self->hi_cap, self->hi_t, t);
    fus_live_step(self->live, (int)kf, (int)self->pi_hc[1], (int64_t)t0, t, (int)h, (int)o, (int64_t)age, rec, inc,
                  v, phi, (fc + 1) % self->sym_every == 0 ? self->sym : NULL);
    b = self->ori->o.pred.bias;
    self->wl[0] = v[3] - b[0];
    self->wl[1] = v[4] - b[1];
    self->wl[2] = v[5] - b[2];
    return PyLong_FromLong(r);
}

/* bind_state(of, learn, ns, opc, ik, mk, ff, ts, fpc, ps, sq, rs, mhc, fref, phi, gap_us, max_gap_us): the
 * owners' per-sample state arrays (ct_sample_state's, in its order; int64) and the source's r* (3) and
 * Phi (3x3, float64), bound once for drain */
static PyObject *ImuSample_bind_state(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const Py_ssize_t len[13] = {CT_OF_N, 1, 2, 1, 2, 2, CT_FF_N, 1, 1, 1, CT_SQ_N, 1, 2};
    static const char *what[13] = {"of", "learn", "ns", "opc", "ik", "mk", "ff", "ts", "fpc", "ps", "sq", "rs",
                                   "mhc"};
    int64_t *p[13];
    long long gap, max_gap;
    int i;
    if (self->ori == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: not bound");
        return NULL;
    }
    if (fus_nargs("bind_state", nargs, 17) < 0 || fus_fresh(&self->sviews, "ImuSample.bind_state") < 0 ||
        fus_long(args[15], &gap) < 0 || fus_long(args[16], &max_gap) < 0)
        return NULL;
    for (i = 0; i < 13; ++i)
        if (!(p[i] = fus_bind(&self->sviews, args[i], len[i], 'q', 1, what[i]))) {
            fus_release(&self->sviews);
            return NULL;
        }
    if (!(self->fref = fus_bind(&self->sviews, args[13], 3, 'd', 0, "fref")) ||
        !(self->phi = fus_bind(&self->sviews, args[14], 9, 'd', 0, "phi"))) {
        fus_release(&self->sviews);
        return NULL;
    }
    self->ss = (struct ct_sample_state){p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11],
                                        p[12], (int64_t)gap, (int64_t)max_gap};
    self->stated = 1;
    Py_RETURN_NONE;
}

/* bind_split(replay, snap_ts): the live state's ext.Replay with its snapshot bound (FusionFilter.live_split_kernel)
 * and the snapshot's InsState.ts, for drain's samples with a snapshot inside their step */
static PyObject *ImuSample_bind_split(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t *ts;
    if (!self->stated) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: bind_split before bind_state");
        return NULL;
    }
    if (fus_nargs("bind_split", nargs, 2) < 0 || fus_fresh(&self->pviews, "ImuSample.bind_split") < 0)
        return NULL;
    if (!ct_py_replay_takes(args[0])) {
        PyErr_SetString(PyExc_TypeError, "bind_split: replay must be an ext.Replay bound to its rings with a snapshot");
        return NULL;
    }
    if (!(ts = fus_bind(&self->pviews, args[1], 1, 'q', 1, "snap_ts")))
        return NULL;
    Py_INCREF(args[0]);
    self->replay = args[0];
    self->snap_ts = ts;
    Py_RETURN_NONE;
}

/* the sample at t with a snapshot inside its step (CT_SR_SNAP), as SensorInertial._sample_python runs it on the
 * compiled core: _Ori.step (ct_ori_sample, or ct_ori_sample_ortho where its prediction is the 64th) with its
 * bookkeeping; FusionFilter.push_imu's InertialPrediction.push (the IMU ring's row), FusionFilter._advance's
 * split_take (OrientationFilter.propagate, then Replay.replay_take through py_fusion.h, InsState.set_time,
 * CovariancePredict.set_count, InertialPrediction.add_steps, Snapshot.taken) and _output (PoseOutput.queue);
 * w_last.  0, or -1 with an exception set */
static int imu_sample_snap(ImuSampleObject *self, const double *phi)
{
    const struct ct_sample_state *s = &self->ss;
    FusLiveObject *lv = self->live;
    FusPredObject *pr = lv->pred;
    FusOutputObject *out = lv->out;
    const double *d, *b;
    double *row;
    int64_t k, t, kf, h, o, io[4], steps = s->of[CT_OF_STEPS], pending = s->sq[CT_SQ_PENDING];
    int r, i, xi;
    k = ct_ring_pop(self->in_hc, self->in_cap);
    t = self->in_t[k];
    d = self->in_d + 6 * k;
    if (((steps + 1) & CT_ORI_ORTHO_MASK) == 0)             /* _Ori.step (step_python's kernels) */
        r = ct_ori_sample_ortho(&self->ori->o, t, d[0], d[1], d[2], d[3], d[4], d[5], s->of[CT_OF_T], (int)s->ns[0],
                                s->mhc[0], s->mhc[1], s->opc[0], s->ik[0], s->mk[0], steps);
    else
        r = ct_ori_sample(&self->ori->o, t, d[0], d[1], d[2], d[3], d[4], d[5], s->of[CT_OF_T], (int)s->ns[0],
                          s->mhc[0], s->mhc[1], s->opc[0], s->ik[0], s->mk[0]);
    ct_sample_done_ori(s, t, r);
    kf = ct_ring_push(self->pi_hc, self->pi_cap, self->pi_t, t);     /* InertialPrediction.push */
    row = lv->row->idv + (long)kf * CT_IMU_WIDTH;
    for (i = 0; i < 6; ++i)
        row[CT_IMU_F + i] = d[i];
    for (i = 0; i < 3; ++i)
        row[CT_IMU_FSRC + i] = self->fref[i];
    if (pr->moving)
        for (i = 0; i < 9; ++i)
            row[CT_IMU_PHI + i] = phi[i];
    xi = s->of[CT_OF_INIT] != 0;                            /* CompiledReplay.split_take */
    if (xi)
        s->opc[0] += ct_ori_propagate_now(&self->ori->o, s->opc[0]);
    if (ct_py_replay_split_take(self->replay, s->ts[0], pending, s->sq[CT_SQ_T], s->fpc[0], xi, io) < 0)
        return -1;
    s->ts[0] = io[0];
    s->fpc[0] = io[1];
    s->ps[0] += io[2];
    if (pending && !io[3]) {                                /* Snapshot.taken */
        self->snap_ts[0] = s->sq[CT_SQ_T];
        s->sq[CT_SQ_XI] = xi;
        s->sq[CT_SQ_PENDING] = 0;
        s->sq[CT_SQ_VALID] = 1;
        s->sq[CT_SQ_INIT] = 1;
    }
    b = self->ori->o.pred.bias;                             /* SensorInertial.w_last */
    self->wl[0] = d[3] - b[0];
    self->wl[1] = d[4] - b[1];
    self->wl[2] = d[5] - b[2];
    o = ct_ring_push(self->ou_hc, self->ou_cap, self->ou_t, t);      /* FusionFilter._output */
    h = self->hi_hc[0] - 1;
    if (h < 0)
        h += self->hi_cap;
    ct_fus_output(out->od + (long)o * CT_OUT_WIDTH, lv->hd + (long)h * CT_HIST_WIDTH, out->P, out->n, out->Th, row,
                  out->moving,
                  (double)ct_fus_status(t - s->ff[CT_FF_UPDATE_T], (int64_t)out->stale_us, (int64_t)out->dr_after_us,
                                        (int64_t)out->dr_limit_us, s->rs[0] != 0,
                                        (s->ff[CT_FF_FLAGS] & ~(int64_t)CT_FUS_FRESH_FLAGS) != 0));
    return 0;
}

/* drain(max_steps) -> 4 n + why: track.burst_fusion._OneCall.run's loop over the samples both filters take
 * whole (ct_sample_route), each through sample's work with its arguments read from the bound state and
 * its bookkeeping done there (ct_sample_done), one whose prediction may orthonormalise the orientation
 * (CT_SR_ORTHO) with it (ct_ori_sample_ortho); n samples run, then why: 0 the ring is empty or
 * max_steps are run, CT_SR_SLOW the oldest sample is the caller's (not run; a full output queue is
 * CT_SR_SLOW, as sample's -1) */
static long long imu_sample_drain(ImuSampleObject *self, long long max)
{
    const struct ct_sample_state *s = &self->ss;
    double v[9], phi[9];
    int64_t t, p, n = 0;
    int why = 0, r, i;
    if (!self->stated) {
        PyErr_SetString(PyExc_RuntimeError, "ImuSample: drain before bind_state");
        return -1;
    }
    for (i = 0; i < 9; ++i)
        phi[i] = self->phi[i];
    while (n < max && self->in_hc[1] > 0) {
        p = self->in_hc[0] - self->in_hc[1];
        if (p < 0)
            p += self->in_cap;
        t = self->in_t[p];
        why = ct_sample_route(s, t);
        if (why != CT_SR_SLOW && self->ou_hc[1] == self->ou_cap)
            why = CT_SR_SLOW;
        if (why == CT_SR_SNAP && (self->replay == NULL || self->pi_hc[1] < 1))
            why = CT_SR_SLOW;           /* (FusionFilter._advance's split kernel wants the sample before it) */
        if (why == CT_SR_SLOW)
            break;
        if (s->mhc[0] < 0 || s->mhc[0] >= self->ori->o.q.cap || s->mhc[1] < 0 || s->mhc[1] > self->ori->o.q.cap) {
            PyErr_SetString(PyExc_IndexError, "drain: head or count outside the magnetometer ring");
            return -1;
        }
        if (why == CT_SR_SNAP) {
            if (imu_sample_snap(self, phi) < 0)
                return -1;
            why = 0;
            ++n;
            continue;
        }
        for (i = 0; i < 3; ++i)
            v[6 + i] = self->fref[i];
        r = imu_sample_whole(self, s->ts[0], t - s->ff[CT_FF_UPDATE_T], s->rs[0] != 0,
                             (s->ff[CT_FF_FLAGS] & ~(int64_t)CT_FUS_FRESH_FLAGS) != 0, s->fpc[0], v, phi,
                             s->of[CT_OF_T], s->ns[0], s->mhc[0], s->mhc[1], s->opc[0], s->ik[0], s->mk[0],
                             why == CT_SR_ORTHO ? s->of[CT_OF_STEPS] : -1);
        ct_sample_done(s, t, r);
        why = 0;
        ++n;
    }
    return (long long)(4 * n + why);
}

static PyObject *ImuSample_drain(ImuSampleObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long max, r;
    if (fus_nargs("drain", nargs, 1) < 0 || fus_long(args[0], &max) < 0)
        return NULL;
    r = imu_sample_drain(self, max);
    return r < 0 ? NULL : PyLong_FromLongLong(r);
}

static PyMethodDef ImuSample_methods[] = {
    {"bind_state", (PyCFunction)(void (*)(void))ImuSample_bind_state, METH_FASTCALL,
     "bind_state(of, learn, ns, opc, ik, mk, ff, ts, fpc, ps, sq, rs, mhc, fref, phi, gap_us, max_gap_us): the "
     "per-sample state drain reads and writes"},
    {"bind_split", (PyCFunction)(void (*)(void))ImuSample_bind_split, METH_FASTCALL,
     "bind_split(replay, snap_ts): the live state's ext.Replay with its snapshot, and the snapshot state's time, "
     "for drain's samples with a snapshot inside their step"},
    {"drain", (PyCFunction)(void (*)(void))ImuSample_drain, METH_FASTCALL,
     "drain(max_steps) -> 4 n + why: the samples both filters take whole (an orthonormalising one too), n of "
     "them run; why 0 (empty or max_steps), 1 (the next is the steps one by one: the caller's)"},
    {"begin", (PyCFunction)(void (*)(void))ImuSample_begin, METH_FASTCALL,
     "begin(t_prev, head, count) -> bits or -1: sample's first half (up to the orientation's prediction)"},
    {"finish", (PyCFunction)(void (*)(void))ImuSample_finish, METH_FASTCALL,
     "finish(t0, age, recovering, inconsistent, fcount, rx, ry, rz, Phi, n, pcount, icount, mcount) -> bits: "
     "sample's second half (the update round and the fusion filter's step) of the sample begin took"},
    {"peek", (PyCFunction)(void (*)(void))ImuSample_peek, METH_FASTCALL,
     "peek() -> the time of the IMU ring's oldest sample, or -1 when it is empty"},
    {"sample", (PyCFunction)(void (*)(void))ImuSample_sample, METH_FASTCALL,
     "sample(t0, age, recovering, inconsistent, fcount, rx, ry, rz, Phi, t_prev, n, head, count, pcount, icount, "
     "mcount) "
     "-> bits: the oldest IMU sample through the orientation filter (OriStep) and the fusion filter (FusLive)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ImuSampleType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ImuSample",
    .tp_basicsize = sizeof(ImuSampleObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "ImuSample(ori, live, in_t, in_d, in_hc, pi_t, pi_hc, hi_t, hi_hc, ou_t, ou_hc, w_last, sym, "
              "symmetrize_every): one IMU "
              "sample of a fused tracker's sensor (its ring, the orientation filter, the fusion filter) in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ImuSample_init,
    .tp_dealloc = (destructor)ImuSample_dealloc,
    .tp_methods = ImuSample_methods,
};

/* --------------------------------------------------------------- FusedTick */
/* track.burst_fusion.BurstFusionTracker._process on the compiled core with a fixed source: each
 * sensor's samples drained in one call (ImuSample.drain, in the sensors' order) with its sample
 * count (SensorInertial.sc) added to, as _OneCall.run adds it; it stops at the first sensor whose
 * drain hands a sample back (the caller runs the rest through the reference loop, from that sensor
 * on: its index and the samples it ran are written into done[0], done[1]). */
typedef struct {
    PyObject_HEAD
    Py_ssize_t n;
    PyObject *held;                 /* the ImuSample objects (tuple) */
    ImuSampleObject **s;
    int64_t **sc;
    int64_t *done;
    Py_buffer *views;               /* the counts, then done */
    Py_ssize_t nv;
} FusedTickObject;

static void FusedTick_dealloc(FusedTickObject *self)
{
    Py_ssize_t k;
    for (k = 0; k < self->nv; ++k)
        PyBuffer_Release(&self->views[k]);
    PyMem_Free(self->views);
    PyMem_Free(self->s);
    PyMem_Free(self->sc);
    Py_XDECREF(self->held);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int FusedTick_init(FusedTickObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"samples", "counts", "done", NULL};
    PyObject *samples, *counts, *done;
    Py_ssize_t n, k;
    if (self->held != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusedTick: already bound");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!O!O", kwlist, &PyTuple_Type, &samples, &PyTuple_Type, &counts,
                                     &done))
        return -1;
    n = PyTuple_GET_SIZE(samples);
    if (n < 1 || PyTuple_GET_SIZE(counts) != n) {
        PyErr_SetString(PyExc_ValueError, "FusedTick: one count per sample kernel, at least one");
        return -1;
    }
    for (k = 0; k < n; ++k)
        if (!PyObject_TypeCheck(PyTuple_GET_ITEM(samples, k), &ImuSampleType) ||
            !((ImuSampleObject *)PyTuple_GET_ITEM(samples, k))->stated) {
            PyErr_SetString(PyExc_TypeError, "FusedTick: samples must be ImuSample objects with their state bound");
            return -1;
        }
    self->s = PyMem_Calloc((size_t)n, sizeof *self->s);
    self->sc = PyMem_Calloc((size_t)n, sizeof *self->sc);
    self->views = PyMem_Calloc((size_t)n + 1, sizeof *self->views);
    if (self->s == NULL || self->sc == NULL || self->views == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (k = 0; k < n; ++k) {
        if (ct_py_buffer(PyTuple_GET_ITEM(counts, k), 1, 8, "ql", 1, &self->views[self->nv], "FusedTick counts") < 0)
            return -1;
        self->sc[k] = self->views[self->nv++].buf;
        self->s[k] = (ImuSampleObject *)PyTuple_GET_ITEM(samples, k);
    }
    if (ct_py_buffer(done, 2, 8, "ql", 1, &self->views[self->nv], "FusedTick done") < 0)
        return -1;
    self->done = self->views[self->nv++].buf;
    Py_INCREF(samples);
    self->held = samples;
    self->n = n;
    return 0;
}

/* process(max_steps) -> 4 n + 2 left + back: n samples run over the sensors, left: a sensor's IMU ring
 * still holds samples (it ran max_steps), back: a sensor's drain handed a sample back (done[0] its
 * index, done[1] the samples it ran; the sensors after it not visited, left then not set) */
static PyObject *FusedTick_process(FusedTickObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    long long max, r, total = 0;
    Py_ssize_t k;
    int left = 0;
    if (self->held == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "FusedTick: not bound");
        return NULL;
    }
    if (fus_nargs("process", nargs, 1) < 0 || fus_long(args[0], &max) < 0)
        return NULL;
    for (k = 0; k < self->n; ++k) {
        r = imu_sample_drain(self->s[k], max);
        if (r < 0)
            return NULL;
        self->sc[k][0] += r >> 2;
        total += r >> 2;
        if (r & 3) {
            self->done[0] = (int64_t)k;
            self->done[1] = (int64_t)(r >> 2);
            return PyLong_FromLongLong(4 * total + 1);
        }
        if (self->s[k]->in_hc[1] > 0)
            left = 1;
    }
    return PyLong_FromLongLong(4 * total + 2 * left);
}

static PyMethodDef FusedTick_methods[] = {
    {"process", (PyCFunction)(void (*)(void))FusedTick_process, METH_FASTCALL,
     "process(max_steps) -> 4 n + 2 left + back: every sensor's ImuSample.drain(max_steps) in order, its count "
     "added to; back: the first sensor that handed a sample back stopped it (done[0] its index, done[1] its "
     "samples run)"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject FusedTickType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.FusedTick",
    .tp_basicsize = sizeof(FusedTickObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "FusedTick(samples, counts, done): a fused tracker's sensors' ImuSample kernels (state bound) and "
              "their sample counts (int64, one each), drained in one call",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)FusedTick_init,
    .tp_dealloc = (destructor)FusedTick_dealloc,
    .tp_methods = FusedTick_methods,
};

/* --------------------------------------------------------------- ImuPush */
/* measure.imu.ImuRing.push of a received sample (receive.ImuRecord or any object with its fields) on
 * the compiled core: the ring's times, rows, head and count and its state (CT_IR_*) bound once; the
 * record's fields read by name (the names interned at construction) */
typedef struct {
    PyObject_HEAD
    int64_t *t, *hc, *st;
    double *d;
    int64_t cap;
    double acc_lsb, gyr_lsb;
    PyObject *names[7];             /* t_us, ax, ay, az, gx, gy, gz */
    fus_views views;
} ImuPushObject;

static void ImuPush_dealloc(ImuPushObject *self)
{
    int i;
    for (i = 0; i < 7; ++i)
        Py_XDECREF(self->names[i]);
    fus_release(&self->views);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int ImuPush_init(ImuPushObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"t", "d", "hc", "st", "acc_lsb", "gyr_lsb", NULL};
    static const char *fields[7] = {"t_us", "ax", "ay", "az", "gx", "gy", "gz"};
    PyObject *t, *d, *hc, *st;
    Py_ssize_t n;
    int i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOdd", kwlist, &t, &d, &hc, &st, &self->acc_lsb, &self->gyr_lsb))
        return -1;
    if (fus_fresh(&self->views, "ImuPush") < 0)
        return -1;
    n = PyObject_Length(t);
    if (n < 1) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "ImuPush: t needs at least 1 slot");
        return -1;
    }
    if (!(self->t = fus_bind(&self->views, t, n, 'q', 1, "t")) ||
        !(self->d = fus_bind(&self->views, d, n * 6, 'd', 1, "d")) ||
        !(self->hc = fus_bind(&self->views, hc, 2, 'q', 1, "hc")) ||
        !(self->st = fus_bind(&self->views, st, CT_IR_N, 'q', 1, "st"))) {
        fus_release(&self->views);
        return -1;
    }
    self->cap = n;
    for (i = 0; i < 7; ++i)
        if (!(self->names[i] = PyUnicode_InternFromString(fields[i]))) {
            fus_release(&self->views);
            return -1;
        }
    return 0;
}

/* push(msg): ImuRing.push(msg) */
static PyObject *ImuPush_push(ImuPushObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double s[6];
    long long t;
    PyObject *v;
    int i;
    if (self->t == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ImuPush: not bound");
        return NULL;
    }
    if (fus_nargs("push", nargs, 1) < 0)
        return NULL;
    if (!(v = PyObject_GetAttr(args[0], self->names[0])))
        return NULL;
    t = PyLong_AsLongLong(v);
    Py_DECREF(v);
    if (t == -1 && PyErr_Occurred())
        return NULL;
    for (i = 0; i < 6; ++i) {
        if (!(v = PyObject_GetAttr(args[0], self->names[1 + i])))
            return NULL;
        if (fus_double(v, &s[i]) < 0) {
            Py_DECREF(v);
            return NULL;
        }
        Py_DECREF(v);
    }
    ct_imu_ring_push(self->hc, self->cap, self->t, self->d, self->st, (int64_t)t, s, self->acc_lsb, self->gyr_lsb);
    Py_RETURN_NONE;
}

static PyMethodDef ImuPush_methods[] = {
    {"push", (PyCFunction)(void (*)(void))ImuPush_push, METH_FASTCALL,
     "push(msg): measure.imu.ImuRing.push of the sample msg (t_us, ax..az, gx..gz) into the bound ring"},
    {NULL, NULL, 0, NULL}};

FUS_TYPE(ImuPush, "ImuPush", "ImuPush(t, d, hc, st, acc_lsb, gyr_lsb): measure.imu.ImuRing.push bound to a ring")

/* --------------------------------------------------------------- register */
int ct_register_fusimu(PyObject *m)
{
    if (ct_py_add_type(m, &FusPredType, "FusPred") < 0 || ct_py_add_type(m, &FusRowType, "FusRow") < 0 ||
        ct_py_add_type(m, &FusOutputType, "FusOutput") < 0 || ct_py_add_type(m, &OriPredType, "OriPred") < 0 ||
        ct_py_add_type(m, &OriUpdType, "OriUpd") < 0 ||
        ct_py_add_type(m, &FusLiveType, "FusLive") < 0 || ct_py_add_type(m, &QuietSampleType, "QuietSample") < 0 ||
        ct_py_add_type(m, &OriStepType, "OriStep") < 0 ||
        ct_py_add_type(m, &ImuSampleType, "ImuSample") < 0 || ct_py_add_type(m, &ImuPushType, "ImuPush") < 0 ||
        ct_py_add_type(m, &FusedTickType, "FusedTick") < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "FUS_IMU_WIDTH", CT_IMU_WIDTH) < 0 ||
        PyModule_AddIntConstant(m, "FUS_HIST_WIDTH", CT_HIST_WIDTH) < 0 ||
        PyModule_AddIntConstant(m, "FUS_OUT_WIDTH", CT_OUT_WIDTH) < 0 ||
        PyModule_AddIntConstant(m, "FUS_OA_N", CT_OA_N) < 0 || PyModule_AddIntConstant(m, "FUS_NST", CT_FS_NST) < 0 ||
        PyModule_AddIntConstant(m, "FUS_CS_N", CT_CS_N) < 0 || PyModule_AddIntConstant(m, "FUS_FL_N", CT_FL_N) < 0 ||
        PyModule_AddIntConstant(m, "FUS_FI_N", CT_FI_COUNT) < 0 || PyModule_AddIntConstant(m, "FUS_IN_N", CT_IN_N) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "FUS_IR_N", CT_IR_N) < 0)
        return -1;
    return 0;
}
