/*
 * CPython glue of the AC kernels (include/ct_ac.h): Demod binds a Demodulator's numpy arrays
 * (and its channel's sample ring) once at construction; Raab binds a Raab tracker's buffers.
 * RaabCorr binds the exact-loop correction's, RaabCov the covariance's. The per-call methods use
 * METH_FASTCALL and write into the bound buffers (RaabCorr's read their per-call arrays in place);
 * they return None, a bool, a small int of flag bits or (Demod.push only) the completed block's index.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "coiltrack_core.h"
#include "py_glue.h"

/* a C-contiguous buffer of at least n items of `itemsize` bytes whose format is one of `formats`
 * (writable when asked), or -1 with TypeError naming `what` */
static int ac_buffer(PyObject *obj, Py_ssize_t n, Py_ssize_t itemsize, const char *formats, int writable,
                     Py_buffer *view, const char *what)
{
    return ct_py_buffer(obj, n, itemsize, formats, writable, view, what);
}

#define F64 8, "d"
#define I64 8, "ql"
#define U8 1, "B"

static int ac_int64(PyObject *o, int64_t *v)
{
    return ct_py_int64(o, v);
}

static int ac_double(PyObject *o, double *x)
{
    return ct_py_double(o, x);
}

static int ac_nargs(const char *name, Py_ssize_t nargs, Py_ssize_t want)
{
    return ct_py_nargs(name, nargs, want);
}

/* ------------------------------------------------------------------- Demod */
enum { DM_FREQS, DM_H, DM_CPH, DM_SPH, DM_G, DM_R, DM_BB, DM_COUNT, DM_FLAGS, DM_KSLOT, DM_PHI, DM_GF, DM_L,
       DM_GINV, DM_X, DM_B, DM_XX, DM_S, DM_Q, DM_VAR, DM_QVAR, DM_DC, DM_ST, DM_OUT, DM_NBUF };
enum { DM_RT, DM_RB, DM_RF, DM_NRING };

typedef struct {
    PyObject_HEAD
    struct ct_demod d;
    Py_buffer views[DM_NBUF], ring[DM_NRING], phase;
    int64_t cap;
    int nbound, ring_bound, phase_bound;
} DemodObject;

static void Demod_release(DemodObject *self)
{
    int i;
    for (i = 0; i < self->nbound; ++i)
        PyBuffer_Release(&self->views[i]);
    self->nbound = 0;
    if (self->ring_bound)
        for (i = 0; i < DM_NRING; ++i)
            PyBuffer_Release(&self->ring[i]);
    self->ring_bound = 0;
    if (self->phase_bound)
        PyBuffer_Release(&self->phase);
    self->phase_bound = 0;
}

static void Demod_dealloc(DemodObject *self)
{
    Demod_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Demod(n, slots, window_us, hop_us, sigma2, bufs, ring[, phase]): bufs the 24 arrays in the order of
 * Demodulator._bind; ring None or (t, b, flags) of the channel's SampleRing; phase None or the drive's
 * measured current phases (n, the actuation's array: step reads them) */
static int Demod_init(DemodObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "slots", "window_us", "hop_us", "sigma2", "bufs", "ring", "phase", NULL};
    static const char *names[DM_NBUF] = {"freqs", "h", "cph", "sph", "G", "R", "BB", "count", "flags", "kslot",
                                         "phi", "Gf", "L", "Ginv", "x", "b", "X", "S", "Q", "var", "qvar", "dc",
                                         "st", "out"};
    int n, slots, i, p;
    long long window_us, hop_us;
    double sigma2;
    PyObject *bufs, *ring, *phase = Py_None;
    Py_ssize_t want[DM_NBUF];
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iiLLdOO|O", kwlist, &n, &slots, &window_us, &hop_us, &sigma2, &bufs,
                                     &ring, &phase))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Demod: already bound");
        return -1;
    }
    if (n < 1 || n > 64 || slots < 1 || window_us < 1 || hop_us < 1) {
        PyErr_SetString(PyExc_ValueError, "Demod: n in 1..64, slots, window_us and hop_us >= 1");
        return -1;
    }
    if (!PyTuple_Check(bufs) || PyTuple_GET_SIZE(bufs) != DM_NBUF) {
        PyErr_Format(PyExc_TypeError, "Demod: bufs must be a tuple of %d arrays", DM_NBUF);
        return -1;
    }
    p = 2 + 2 * n;
    want[DM_FREQS] = n; want[DM_H] = 2 * n; want[DM_CPH] = n; want[DM_SPH] = n;
    want[DM_G] = (Py_ssize_t)slots * p * p; want[DM_R] = (Py_ssize_t)slots * 3 * p; want[DM_BB] = 3 * slots;
    want[DM_COUNT] = want[DM_FLAGS] = want[DM_KSLOT] = slots;
    want[DM_PHI] = p; want[DM_GF] = want[DM_L] = want[DM_GINV] = p * p; want[DM_X] = want[DM_B] = p;
    want[DM_XX] = 3 * p; want[DM_S] = want[DM_Q] = want[DM_VAR] = 3 * n; want[DM_QVAR] = n; want[DM_DC] = 3;
    want[DM_ST] = CT_DM_NST; want[DM_OUT] = CT_DMO_N;
    for (i = 0; i < DM_NBUF; ++i) {
        int is_int = i == DM_COUNT || i == DM_FLAGS || i == DM_KSLOT || i == DM_ST;
        int ro = i == DM_FREQS || i == DM_H;
        if (ac_buffer(PyTuple_GET_ITEM(bufs, i), want[i], 8, is_int ? "ql" : "d", !ro, &self->views[i],
                      names[i]) < 0) {
            Demod_release(self);
            return -1;
        }
        self->nbound = i + 1;
    }
    if (ring != Py_None) {
        if (!PyTuple_Check(ring) || PyTuple_GET_SIZE(ring) != 3) {
            Demod_release(self);
            PyErr_SetString(PyExc_TypeError, "Demod: ring must be None or (t, b, flags)");
            return -1;
        }
        if (ac_buffer(PyTuple_GET_ITEM(ring, 0), 2, I64, 0, &self->ring[DM_RT], "ring t") < 0) {
            Demod_release(self);
            return -1;
        }
        self->cap = (int64_t)(self->ring[DM_RT].len / 8);
        if (ac_buffer(PyTuple_GET_ITEM(ring, 1), 3 * self->cap, F64, 0, &self->ring[DM_RB], "ring b") < 0) {
            PyBuffer_Release(&self->ring[DM_RT]);
            Demod_release(self);
            return -1;
        }
        if (ac_buffer(PyTuple_GET_ITEM(ring, 2), self->cap, U8, 0, &self->ring[DM_RF], "ring flags") < 0) {
            PyBuffer_Release(&self->ring[DM_RT]);
            PyBuffer_Release(&self->ring[DM_RB]);
            Demod_release(self);
            return -1;
        }
        self->ring_bound = 1;
    }
    if (phase != Py_None) {
        if (ac_buffer(phase, n, 8, "d", 0, &self->phase, "phase") < 0) {
            Demod_release(self);
            return -1;
        }
        self->phase_bound = 1;
    }
#define DBUF(i) ((double *)self->views[i].buf)
#define IBUF(i) ((int64_t *)self->views[i].buf)
    self->d.n = n;
    self->d.p = p;
    self->d.slots = slots;
    self->d.window_us = (int64_t)window_us;
    self->d.hop_us = (int64_t)hop_us;
    self->d.sigma2 = sigma2;
    self->d.freqs = DBUF(DM_FREQS); self->d.h = DBUF(DM_H); self->d.cph = DBUF(DM_CPH); self->d.sph = DBUF(DM_SPH);
    self->d.G = DBUF(DM_G); self->d.R = DBUF(DM_R); self->d.BB = DBUF(DM_BB);
    self->d.count = IBUF(DM_COUNT); self->d.flags = IBUF(DM_FLAGS); self->d.kslot = IBUF(DM_KSLOT);
    self->d.phi = DBUF(DM_PHI); self->d.Gf = DBUF(DM_GF); self->d.L = DBUF(DM_L); self->d.Ginv = DBUF(DM_GINV);
    self->d.x = DBUF(DM_X); self->d.b = DBUF(DM_B); self->d.X = DBUF(DM_XX);
    self->d.S = DBUF(DM_S); self->d.Q = DBUF(DM_Q); self->d.var = DBUF(DM_VAR); self->d.qvar = DBUF(DM_QVAR);
    self->d.dc = DBUF(DM_DC); self->d.st = IBUF(DM_ST); self->d.out = DBUF(DM_OUT);
#undef DBUF
#undef IBUF
    return 0;
}

static int Demod_ready(DemodObject *self)
{
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Demod: not bound");
        return -1;
    }
    return 0;
}

/* push(t, bx, by, bz, sample_flags) -> k or -1 */
static PyObject *Demod_push(DemodObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t t, fl;
    double bx, by, bz;
    if (Demod_ready(self) < 0 || ac_nargs("push", nargs, 5) < 0)
        return NULL;
    if (ac_int64(args[0], &t) < 0 || ac_double(args[1], &bx) < 0 || ac_double(args[2], &by) < 0 ||
        ac_double(args[3], &bz) < 0 || ac_int64(args[4], &fl) < 0)
        return NULL;
    return PyLong_FromLongLong((long long)ct_demod_push(&self->d, t, bx, by, bz, fl));
}

/* feed(count, last, left) -> bool: the bound ring's new samples (count entries, the newest in slot last) */
static PyObject *Demod_feed(DemodObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t count, last, left;
    if (Demod_ready(self) < 0 || ac_nargs("feed", nargs, 3) < 0)
        return NULL;
    if (!self->ring_bound) {
        PyErr_SetString(PyExc_RuntimeError, "Demod: no ring bound");
        return NULL;
    }
    if (ac_int64(args[0], &count) < 0 || ac_int64(args[1], &last) < 0 || ac_int64(args[2], &left) < 0)
        return NULL;
    if (count < 0 || count > self->cap || (count > 0 && (last < 0 || last >= self->cap))) {
        PyErr_SetString(PyExc_ValueError, "feed: count or last outside the ring");
        return NULL;
    }
    if (ct_demod_feed(&self->d, (const int64_t *)self->ring[DM_RT].buf, (const double *)self->ring[DM_RB].buf,
                      (const uint8_t *)self->ring[DM_RF].buf, self->cap, count, last, left))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* step(count, last, left, signal_gate, ratio_max, q_gate) -> int: the CT_DMS_* bits of ct_demod_step over
 * the bound ring (count entries, the newest in slot last) and the bound phases */
static PyObject *Demod_step(DemodObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t count, last, left;
    double sg, rm, qg;
    if (Demod_ready(self) < 0 || ac_nargs("step", nargs, 6) < 0)
        return NULL;
    if (!self->ring_bound || !self->phase_bound) {
        PyErr_SetString(PyExc_RuntimeError, "Demod: no ring or no phases bound");
        return NULL;
    }
    if (ac_int64(args[0], &count) < 0 || ac_int64(args[1], &last) < 0 || ac_int64(args[2], &left) < 0 ||
        ac_double(args[3], &sg) < 0 || ac_double(args[4], &rm) < 0 || ac_double(args[5], &qg) < 0)
        return NULL;
    if (count < 0 || count > self->cap || (count > 0 && (last < 0 || last >= self->cap))) {
        PyErr_SetString(PyExc_ValueError, "step: count or last outside the ring");
        return NULL;
    }
    return PyLong_FromLong(ct_demod_step(&self->d, (const double *)self->phase.buf,
                                         (const int64_t *)self->ring[DM_RT].buf, (const double *)self->ring[DM_RB].buf,
                                         (const uint8_t *)self->ring[DM_RF].buf, self->cap, count, last, left, sg,
                                         rm, qg));
}

/* finish(k) -> bool */
static PyObject *Demod_finish(DemodObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int64_t k;
    if (Demod_ready(self) < 0 || ac_nargs("finish", nargs, 1) < 0 || ac_int64(args[0], &k) < 0)
        return NULL;
    if (k < 0) {
        PyErr_SetString(PyExc_ValueError, "finish: k must be >= 0");
        return NULL;
    }
    if (ct_demod_finish(&self->d, k))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef Demod_methods[] = {
    {"push", (PyCFunction)(void (*)(void))Demod_push, METH_FASTCALL,
     "push(t, bx, by, bz, sample_flags) -> k: as Demodulator.push"},
    {"feed", (PyCFunction)(void (*)(void))Demod_feed, METH_FASTCALL,
     "feed(count, last, left) -> bool: as Demodulator.feed over the bound ring"},
    {"step", (PyCFunction)(void (*)(void))Demod_step, METH_FASTCALL,
     "step(count, last, left, signal_gate, ratio_max, q_gate) -> int: as Demodulator.step"},
    {"finish", (PyCFunction)(void (*)(void))Demod_finish, METH_FASTCALL,
     "finish(k) -> bool: as Demodulator.finish, with the block's statistics into out"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject DemodType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Demod",
    .tp_basicsize = sizeof(DemodObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "One demodulator's buffers bound for ct_demod_push / feed / finish (measure.demod.Demodulator)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Demod_init,
    .tp_dealloc = (destructor)Demod_dealloc,
    .tp_methods = Demod_methods,
};

/* ---------------------------------------------------------------- ACBlocks */
enum { AB_RT, AB_RB, AB_RF, AB_S, AB_VAR, AB_FLAGS, AB_PMID, AB_DONE, AB_NCH };   /* per channel */
enum { AB_PHASE, AB_AMP, AB_SSTART, AB_SEND, AB_SMEAS, AB_SK, AB_DIST, AB_QR, AB_ST, AB_FS, AB_RS, AB_NSH };

typedef struct {
    PyObject_HEAD
    struct ct_ac_blocks a;
    struct ct_ac_channel ch[CT_ACB_MAX_CH];
    PyObject *demod[CT_ACB_MAX_CH];
    Py_buffer cv[CT_ACB_MAX_CH][AB_NCH], sv[AB_NSH];
    int ncv[CT_ACB_MAX_CH], nsv, nch_bound;
    int64_t *rs;
} ACBlocksObject;

static void ACBlocks_release(ACBlocksObject *self)
{
    int i, j;
    for (i = 0; i < self->nch_bound; ++i) {
        for (j = 0; j < self->ncv[i]; ++j)
            PyBuffer_Release(&self->cv[i][j]);
        self->ncv[i] = 0;
        Py_CLEAR(self->demod[i]);
    }
    self->nch_bound = 0;
    for (j = 0; j < self->nsv; ++j)
        PyBuffer_Release(&self->sv[j]);
    self->nsv = 0;
    self->a.nch = 0;
}

static void ACBlocks_dealloc(ACBlocksObject *self)
{
    ACBlocks_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* channel i of `chans`: (Demod, ring t, ring b, ring flags, S, var, flags, pulse_mid, done) */
static int ACBlocks_channel(ACBlocksObject *self, int i, PyObject *item, int n)
{
    static const char *names[AB_NCH] = {"ring t", "ring b", "ring flags", "S", "var", "flags", "pulse_mid",
                                        "done"};
    struct ct_ac_channel *c = &self->ch[i];
    DemodObject *dm;
    int j;
    if (!PyTuple_Check(item) || PyTuple_GET_SIZE(item) != 1 + AB_NCH) {
        PyErr_SetString(PyExc_TypeError, "ACBlocks: each channel must be a tuple of a Demod and 8 arrays");
        return -1;
    }
    if (!PyObject_TypeCheck(PyTuple_GET_ITEM(item, 0), &DemodType)) {
        PyErr_SetString(PyExc_TypeError, "ACBlocks: a channel's first item must be a Demod");
        return -1;
    }
    dm = (DemodObject *)PyTuple_GET_ITEM(item, 0);
    if (!dm->nbound || dm->d.n != n || !dm->ring_bound) {
        PyErr_SetString(PyExc_ValueError, "ACBlocks: a Demod not bound, without its ring, or of another n");
        return -1;
    }
    Py_INCREF(dm);
    self->demod[i] = (PyObject *)dm;
    self->nch_bound = i + 1;
    for (j = 0; j < AB_NCH; ++j) {
        Py_ssize_t want = j == AB_RT || j == AB_RF ? 1 : j == AB_RB ? 3 : j == AB_S || j == AB_VAR ? 3 * n : n;
        const char *fmt = j == AB_RB || j == AB_S || j == AB_VAR ? "d" : j == AB_RF ? "B" : j == AB_DONE ? "?"
                                                                                                          : "ql";
        Py_ssize_t size = j == AB_RF || j == AB_DONE ? 1 : 8;
        if (ac_buffer(PyTuple_GET_ITEM(item, 1 + j), want, size, fmt, j >= AB_S, &self->cv[i][j], names[j]) < 0)
            return -1;
        self->ncv[i] = j + 1;
    }
    c->dm = &dm->d;
    c->cap = (int64_t)(self->cv[i][AB_RT].len / 8);
    if (self->cv[i][AB_RB].len < 3 * c->cap * 8 || self->cv[i][AB_RF].len < c->cap || c->cap != dm->cap) {
        PyErr_SetString(PyExc_ValueError, "ACBlocks: a ring's arrays are not its Demod's");
        return -1;
    }
    c->rt = (const int64_t *)self->cv[i][AB_RT].buf;
    c->rb = (const double *)self->cv[i][AB_RB].buf;
    c->rf = (const uint8_t *)self->cv[i][AB_RF].buf;
    c->S = (double *)self->cv[i][AB_S].buf;
    c->var = (double *)self->cv[i][AB_VAR].buf;
    c->flags = (int64_t *)self->cv[i][AB_FLAGS].buf;
    c->pulse_mid = (int64_t *)self->cv[i][AB_PMID].buf;
    c->done = (uint8_t *)self->cv[i][AB_DONE].buf;
    return 0;
}

/* ACBlocks(n, chans, phase, amplitude, sched_start, sched_end, sched_measured, solved_k, distorted,
 * quad_ratio, st, fs, rs): measure.ac_blocks.ACBlockMeasurement._bind_compiled's arrays */
static int ACBlocks_init(ACBlocksObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "chans", "phase", "amplitude", "sched_start", "sched_end", "sched_measured",
                             "solved_k", "distorted", "quad_ratio", "st", "fs", "rs", NULL};
    static const char *names[AB_NSH] = {"phase", "amplitude", "sched_start", "sched_end", "sched_measured",
                                        "solved_k", "distorted", "quad_ratio", "st", "fs", "rs"};
    PyObject *chans, *sh[AB_NSH];
    int n, nch, i;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "iOOOOOOOOOOOO", kwlist, &n, &chans, &sh[0], &sh[1], &sh[2], &sh[3],
                                     &sh[4], &sh[5], &sh[6], &sh[7], &sh[8], &sh[9], &sh[10]))
        return -1;
    if (self->a.nch) {
        PyErr_SetString(PyExc_RuntimeError, "ACBlocks: already bound");
        return -1;
    }
    if (n < 1 || n > 64 || !PyTuple_Check(chans) || PyTuple_GET_SIZE(chans) < 1 ||
        PyTuple_GET_SIZE(chans) > CT_ACB_MAX_CH) {
        PyErr_Format(PyExc_ValueError, "ACBlocks: n in 1..64 and a tuple of 1..%d channels", CT_ACB_MAX_CH);
        return -1;
    }
    nch = (int)PyTuple_GET_SIZE(chans);
    for (i = 0; i < AB_NSH; ++i) {
        Py_ssize_t want = i <= AB_SMEAS ? n : i == AB_ST ? CT_ACB_NST : i == AB_FS ? CT_ACBF_N
                                                           : i == AB_RS ? 2 * nch : nch;
        int is_int = i == AB_SSTART || i == AB_SEND || i == AB_SK || i == AB_DIST || i == AB_ST || i == AB_RS;
        int ro = i == AB_PHASE || i == AB_AMP || i == AB_RS;
        if (ac_buffer(sh[i], want, 8, is_int ? "ql" : "d", !ro, &self->sv[i], names[i]) < 0) {
            ACBlocks_release(self);
            return -1;
        }
        self->nsv = i + 1;
    }
    for (i = 0; i < nch; ++i)
        if (ACBlocks_channel(self, i, PyTuple_GET_ITEM(chans, i), n) < 0) {
            ACBlocks_release(self);
            return -1;
        }
#define SD(i) ((double *)self->sv[i].buf)
#define SI(i) ((int64_t *)self->sv[i].buf)
    self->a.n = n;
    self->a.ch = self->ch;
    self->a.phase = SD(AB_PHASE);
    self->a.amplitude = SD(AB_AMP);
    self->a.sched_start = SI(AB_SSTART);
    self->a.sched_end = SI(AB_SEND);
    self->a.sched_measured = SD(AB_SMEAS);
    self->a.solved_k = SI(AB_SK);
    self->a.distorted = SI(AB_DIST);
    self->a.quad_ratio = SD(AB_QR);
    self->a.st = SI(AB_ST);
    self->a.fs = SD(AB_FS);
    self->rs = SI(AB_RS);
    self->a.nch = nch;
#undef SD
#undef SI
    return 0;
}

/* step() -> int: ct_ac_blocks_step over the bound rings' counts and last slots (rs) */
static PyObject *ACBlocks_step(ACBlocksObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int i;
    (void)args;
    if (!self->a.nch) {
        PyErr_SetString(PyExc_RuntimeError, "ACBlocks: not bound");
        return NULL;
    }
    if (ac_nargs("step", nargs, 0) < 0)
        return NULL;
    for (i = 0; i < self->a.nch; ++i) {
        int64_t count = self->rs[2 * i], last = self->rs[2 * i + 1], cap = self->ch[i].cap;
        if (count < 0 || count > cap || (count > 0 && (last < 0 || last >= cap))) {
            PyErr_SetString(PyExc_ValueError, "ACBlocks.step: count or last outside a ring");
            return NULL;
        }
    }
    return PyLong_FromLongLong((long long)ct_ac_blocks_step(&self->a, self->rs));
}

static PyMethodDef ACBlocks_methods[] = {
    {"step", (PyCFunction)(void (*)(void))ACBlocks_step, METH_FASTCALL,
     "step() -> int: as ACBlockMeasurement._tick over the bound arrays"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ACBlocksType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.ACBlocks",
    .tp_basicsize = sizeof(ACBlocksObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The AC measure stage's tick bound for ct_ac_blocks_step (measure.ac_blocks.ACBlockMeasurement)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)ACBlocks_init,
    .tp_dealloc = (destructor)ACBlocks_dealloc,
    .tp_methods = ACBlocks_methods,
};

/* -------------------------------------------------------------------- Raab */
enum { RB_PAR, RB_CBAR, RB_S, RB_MP, RB_CUR, RB_SC, RB_F, RB_X, RB_R, RB_PM, RB_B, RB_G, RB_K, RB_PERM, RB_OUT,
       RB_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_raab r;
    Py_buffer views[RB_NBUF];
    int nbound;
} RaabObject;

static void Raab_release(RaabObject *self)
{
    int i;
    for (i = 0; i < self->nbound; ++i)
        PyBuffer_Release(&self->views[i]);
    self->nbound = 0;
}

static void Raab_dealloc(RaabObject *self)
{
    Raab_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Raab(n, corr, par, cbar, S, mp, cur, Sc, F, x, R, pm, b, G, K, perm, out): pose.raab_update.Update's buffers */
static int Raab_init(RaabObject *self, PyObject *args, PyObject *kw)
{
    static const char *names[RB_NBUF] = {"par", "cbar", "S", "mp", "cur", "Sc", "F", "x", "R", "pm", "b", "G", "K",
                                         "perm", "out"};
    PyObject *objs[RB_NBUF];
    Py_ssize_t want[RB_NBUF];
    int n, corr, i;
    if (kw != NULL && PyDict_Size(kw) > 0) {
        PyErr_SetString(PyExc_TypeError, "Raab: positional arguments only");
        return -1;
    }
    if (!PyArg_ParseTuple(args, "ipOOOOOOOOOOOOOOO", &n, &corr, &objs[RB_PAR], &objs[RB_CBAR], &objs[RB_S],
                          &objs[RB_MP], &objs[RB_CUR], &objs[RB_SC], &objs[RB_F], &objs[RB_X], &objs[RB_R],
                          &objs[RB_PM], &objs[RB_B], &objs[RB_G], &objs[RB_K], &objs[RB_PERM], &objs[RB_OUT]))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Raab: already bound");
        return -1;
    }
    if (n < 3 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "Raab: n must be in 3..64");
        return -1;
    }
    want[RB_PAR] = CT_RP_N; want[RB_CBAR] = 3; want[RB_S] = want[RB_MP] = want[RB_SC] = 3 * n; want[RB_CUR] = n;
    want[RB_F] = 9; want[RB_X] = 6; want[RB_R] = 9; want[RB_PM] = 3; want[RB_B] = 3 * n; want[RB_G] = 9 * n;
    want[RB_K] = 36; want[RB_PERM] = 6; want[RB_OUT] = CT_RO_N;
    for (i = 0; i < RB_NBUF; ++i) {
        int ro = i == RB_PAR || i == RB_CBAR || i == RB_S || i == RB_CUR || i == RB_PM ||
                 i == RB_B || i == RB_G || i == RB_K || i == RB_PERM;
        if (ac_buffer(objs[i], want[i], 8, i == RB_PERM ? "ql" : "d", !ro, &self->views[i], names[i]) < 0) {
            Raab_release(self);
            return -1;
        }
        self->nbound = i + 1;
    }
#define DBUF(i) ((double *)self->views[i].buf)
    self->r.n = n;
    self->r.corr = corr;
    self->r.par = DBUF(RB_PAR); self->r.cbar = DBUF(RB_CBAR); self->r.S = DBUF(RB_S); self->r.mp = DBUF(RB_MP);
    self->r.cur = DBUF(RB_CUR); self->r.Sc = DBUF(RB_SC); self->r.F = DBUF(RB_F); self->r.x = DBUF(RB_X);
    self->r.R = DBUF(RB_R); self->r.pm = DBUF(RB_PM); self->r.b = DBUF(RB_B); self->r.G = DBUF(RB_G);
    self->r.K = DBUF(RB_K); self->r.perm = (const int64_t *)self->views[RB_PERM].buf; self->r.out = DBUF(RB_OUT);
#undef DBUF
    return 0;
}

/* update(lin, k_id) -> int: the bits of ct_raab_update */
static PyObject *Raab_update(RaabObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int lin, k_id;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Raab: not bound");
        return NULL;
    }
    if (ac_nargs("update", nargs, 2) < 0)
        return NULL;
    lin = PyObject_IsTrue(args[0]);
    k_id = PyObject_IsTrue(args[1]);
    if (lin < 0 || k_id < 0)
        return NULL;
    return PyLong_FromLong(ct_raab_update(&self->r, lin, k_id));
}

/* couple() -> int: the bits of ct_raab_coupling */
static PyObject *Raab_couple(RaabObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Raab: not bound");
        return NULL;
    }
    if (ac_nargs("couple", nargs, 0) < 0)
        return NULL;
    return PyLong_FromLong(ct_raab_coupling(&self->r));
}

/* pseudo_inverse(mpa, mom) -> bool: the moments per ampere mpa (3 n) at the bound currents into mom (3 n),
 * M^+ into the bound mp (bound writable) */
static PyObject *Raab_pseudo_inverse(RaabObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer a, m;
    int n = self->r.n, ok;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "Raab: not bound");
        return NULL;
    }
    if (ac_nargs("pseudo_inverse", nargs, 2) < 0 || ac_buffer(args[0], 3 * n, F64, 0, &a, "mpa") < 0)
        return NULL;
    if (ac_buffer(args[1], 3 * n, F64, 1, &m, "mom") < 0) {
        PyBuffer_Release(&a);
        return NULL;
    }
    ok = ct_raab_pseudo_inverse(n, (const double *)a.buf, self->r.cur, (double *)m.buf, (double *)self->r.mp);
    PyBuffer_Release(&a);
    PyBuffer_Release(&m);
    if (ok)
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef Raab_methods[] = {
    {"pseudo_inverse", (PyCFunction)(void (*)(void))Raab_pseudo_inverse, METH_FASTCALL,
     "pseudo_inverse(mpa, mom) -> bool: as pose.raab_update.moment_pseudo_inverse into mom and the bound mp"},
    {"couple", (PyCFunction)(void (*)(void))Raab_couple, METH_FASTCALL,
     "couple() -> bits: the corrected signals, F and k, as pose.raab_update.Update.couple"},
    {"update", (PyCFunction)(void (*)(void))Raab_update, METH_FASTCALL,
     "update(lin, k_id) -> bits: one update of Raab's tracker, as pose.raab_update.Update.run"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RaabType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.Raab",
    .tp_basicsize = sizeof(RaabObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A Raab tracker's buffers bound for ct_raab_update (pose.raab_update.Update)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Raab_init,
    .tp_dealloc = (destructor)Raab_dealloc,
    .tp_methods = Raab_methods,
};

/* ---------------------------------------------------------------- RaabCorr */
enum { RC_B, RC_G, RC_K, RC_PERM, RC_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_raab_corr c;
    Py_buffer views[RC_NBUF];
    int nbound;
} RaabCorrObject;

static void RaabCorr_release(RaabCorrObject *self)
{
    int i;
    for (i = 0; i < self->nbound; ++i)
        PyBuffer_Release(&self->views[i]);
    self->nbound = 0;
}

static void RaabCorr_dealloc(RaabCorrObject *self)
{
    RaabCorr_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* RaabCorr(n, c_raab, b, G, K, perm): raab_correction.LoopCorrection's buffers */
static int RaabCorr_init(RaabCorrObject *self, PyObject *args, PyObject *kw)
{
    static const char *names[RC_NBUF] = {"b", "G", "K", "perm"};
    PyObject *objs[RC_NBUF];
    Py_ssize_t want[RC_NBUF];
    int n, i;
    double c_raab;
    if (kw != NULL && PyDict_Size(kw) > 0) {
        PyErr_SetString(PyExc_TypeError, "RaabCorr: positional arguments only");
        return -1;
    }
    if (!PyArg_ParseTuple(args, "idOOOO", &n, &c_raab, &objs[RC_B], &objs[RC_G], &objs[RC_K], &objs[RC_PERM]))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabCorr: already bound");
        return -1;
    }
    if (n < 1 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "RaabCorr: n must be in 1..64");
        return -1;
    }
    want[RC_B] = 3 * n; want[RC_G] = 9 * n; want[RC_K] = 36; want[RC_PERM] = 6;
    for (i = 0; i < RC_NBUF; ++i) {
        if (ac_buffer(objs[i], want[i], 8, i == RC_PERM ? "ql" : "d", 1, &self->views[i], names[i]) < 0) {
            RaabCorr_release(self);
            return -1;
        }
        self->nbound = i + 1;
    }
    self->c.n = n;
    self->c.c_raab = c_raab;
    self->c.b = (double *)self->views[RC_B].buf;
    self->c.G = (double *)self->views[RC_G].buf;
    self->c.K = (double *)self->views[RC_K].buf;
    self->c.perm = (int64_t *)self->views[RC_PERM].buf;
    return 0;
}

static int RaabCorr_ready(RaabCorrObject *self)
{
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabCorr: not bound");
        return -1;
    }
    return 0;
}

/* per-call float64 buffers (the last writable when asked): views[i] of args[i] with at least want[i] items */
static int ac_views(PyObject *const *args, int k, const Py_ssize_t *want, const char *const *names, int writable_last,
                    Py_buffer *views)
{
    int i;
    for (i = 0; i < k; ++i)
        if (ac_buffer(args[i], want[i], F64, writable_last && i == k - 1, &views[i], names[i]) < 0) {
            while (--i >= 0)
                PyBuffer_Release(&views[i]);
            return -1;
        }
    return 0;
}

/* refresh(x, Bv, Jv, mpa, w, cur, ddx, ddy, ddz, shift_ok, out): out = (rel, shift) */
static PyObject *RaabCorr_refresh(RaabCorrObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *const names[7] = {"x", "Bv", "Jv", "mpa", "w", "cur", "out"};
    PyObject *a[7];
    Py_ssize_t want[7];
    Py_buffer v[7];
    double dd[3];
    int n = self->c.n, shift_ok, i;
    if (RaabCorr_ready(self) < 0 || ac_nargs("refresh", nargs, 11) < 0)
        return NULL;
    if (ac_double(args[6], &dd[0]) < 0 || ac_double(args[7], &dd[1]) < 0 || ac_double(args[8], &dd[2]) < 0)
        return NULL;
    shift_ok = PyObject_IsTrue(args[9]);
    if (shift_ok < 0)
        return NULL;
    for (i = 0; i < 6; ++i)
        a[i] = args[i];
    a[6] = args[10];
    want[0] = 6; want[1] = 3 * n; want[2] = 9 * n; want[3] = 3 * n; want[4] = 3 * n; want[5] = n; want[6] = 2;
    if (ac_views(a, 7, want, names, 1, v) < 0)
        return NULL;
    ct_raab_refresh(&self->c, (const double *)v[0].buf, (const double *)v[1].buf, (const double *)v[2].buf,
                    (const double *)v[3].buf, (const double *)v[4].buf, (const double *)v[5].buf, dd, shift_ok,
                    (double *)v[6].buf);
    for (i = 0; i < 7; ++i)
        PyBuffer_Release(&v[i]);
    Py_RETURN_NONE;
}

/* precondition(x, mp, cur, k) -> bool (K factored) */
static PyObject *RaabCorr_precondition(RaabCorrObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *const names[3] = {"x", "mp", "cur"};
    Py_ssize_t want[3];
    Py_buffer v[3];
    double k;
    int n = self->c.n, ok, i;
    if (RaabCorr_ready(self) < 0 || ac_nargs("precondition", nargs, 4) < 0)
        return NULL;
    if (ac_double(args[3], &k) < 0)
        return NULL;
    want[0] = 6; want[1] = 3 * n; want[2] = n;
    if (ac_views(args, 3, want, names, 0, v) < 0)
        return NULL;
    ok = ct_raab_precondition(&self->c, (const double *)v[0].buf, (const double *)v[1].buf,
                              (const double *)v[2].buf, k);
    for (i = 0; i < 3; ++i)
        PyBuffer_Release(&v[i]);
    if (ok)
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef RaabCorr_methods[] = {
    {"refresh", (PyCFunction)(void (*)(void))RaabCorr_refresh, METH_FASTCALL,
     "refresh(x, Bv, Jv, mpa, w, cur, ddx, ddy, ddz, shift_ok, out): as LoopCorrection.refresh, (rel, shift) "
     "into out"},
    {"precondition", (PyCFunction)(void (*)(void))RaabCorr_precondition, METH_FASTCALL,
     "precondition(x, mp, cur, k) -> bool: K and its LU factors, as LoopCorrection.precondition"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RaabCorrType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.RaabCorr",
    .tp_basicsize = sizeof(RaabCorrObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The exact-loop correction's buffers bound for ct_raab_refresh / ct_raab_precondition",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RaabCorr_init,
    .tp_dealloc = (destructor)RaabCorr_dealloc,
    .tp_methods = RaabCorr_methods,
};

/* ----------------------------------------------------------------- RaabCov */
enum { RV_PAR, RV_CBAR, RV_COV, RV_K, RV_H, RV_Q, RV_QM, RV_A, RV_CS, RV_PC, RV_ST, RV_T, RV_L, RV_M, RV_X, RV_R,
       RV_W, RV_CUR, RV_PM, RV_BV, RV_JV, RV_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_raab_cov c;
    const double *x, *R, *w, *cur, *pm, *Bv, *Jv;
    Py_buffer views[RV_NBUF];
    int nbound;
} RaabCovObject;

static void RaabCov_release(RaabCovObject *self)
{
    int i;
    for (i = 0; i < self->nbound; ++i)
        PyBuffer_Release(&self->views[i]);
    self->nbound = 0;
}

static void RaabCov_dealloc(RaabCovObject *self)
{
    RaabCov_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* RaabCov(n, bufs): bufs the 21 arrays par, cbar, cov, K, H, q, qm, A, Cs, pc, st, T, L, M (its own) and
 * x, R, w, cur, pm, Bv, Jv (the tracker's and its signal model's, read per call) */
static int RaabCov_init(RaabCovObject *self, PyObject *args, PyObject *kw)
{
    static const char *names[RV_NBUF] = {"par", "cbar", "cov", "K", "H", "q", "qm", "A", "Cs", "pc", "st", "T", "L",
                                         "M", "x", "R", "w", "cur", "pm", "Bv", "Jv"};
    PyObject *bufs;
    Py_ssize_t want[RV_NBUF];
    int n, i;
    if (kw != NULL && PyDict_Size(kw) > 0) {
        PyErr_SetString(PyExc_TypeError, "RaabCov: positional arguments only");
        return -1;
    }
    if (!PyArg_ParseTuple(args, "iO", &n, &bufs))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabCov: already bound");
        return -1;
    }
    if (n < 3 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "RaabCov: n must be in 3..64");
        return -1;
    }
    if (!PyTuple_Check(bufs) || PyTuple_GET_SIZE(bufs) != RV_NBUF) {
        PyErr_Format(PyExc_TypeError, "RaabCov: bufs must be a tuple of %d arrays", RV_NBUF);
        return -1;
    }
    want[RV_PAR] = CT_RCP_N; want[RV_CBAR] = 3; want[RV_COV] = 36; want[RV_K] = want[RV_H] = 18 * n;
    want[RV_Q] = 3 * n; want[RV_QM] = n; want[RV_A] = want[RV_CS] = 36; want[RV_PC] = 3; want[RV_ST] = CT_RCS_N;
    want[RV_T] = want[RV_L] = want[RV_M] = 36; want[RV_X] = 6; want[RV_R] = 9; want[RV_W] = 3 * n; want[RV_CUR] = n;
    want[RV_PM] = 3; want[RV_BV] = 3 * n; want[RV_JV] = 9 * n;
    for (i = 0; i < RV_NBUF; ++i) {
        int ro = i == RV_PAR || i == RV_CBAR || i >= RV_X;
        if (ac_buffer(PyTuple_GET_ITEM(bufs, i), want[i], F64, !ro, &self->views[i], names[i]) < 0) {
            RaabCov_release(self);
            return -1;
        }
        self->nbound = i + 1;
    }
#define DBUF(i) ((double *)self->views[i].buf)
    self->c.n = n;
    self->c.par = DBUF(RV_PAR); self->c.cbar = DBUF(RV_CBAR); self->c.cov = DBUF(RV_COV);
    self->c.K = DBUF(RV_K); self->c.H = DBUF(RV_H); self->c.q = DBUF(RV_Q); self->c.qm = DBUF(RV_QM);
    self->c.A = DBUF(RV_A); self->c.Cs = DBUF(RV_CS); self->c.pc = DBUF(RV_PC); self->c.st = DBUF(RV_ST);
    self->c.T = DBUF(RV_T); self->c.L = DBUF(RV_L); self->c.M = DBUF(RV_M);
    self->x = DBUF(RV_X); self->R = DBUF(RV_R); self->w = DBUF(RV_W); self->cur = DBUF(RV_CUR);
    self->pm = DBUF(RV_PM); self->Bv = DBUF(RV_BV); self->Jv = DBUF(RV_JV);
#undef DBUF
    return 0;
}

static int RaabCov_ready(RaabCovObject *self)
{
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabCov: not bound");
        return -1;
    }
    return 0;
}

/* rows(): the bound Bv, Jv into K */
static PyObject *RaabCov_rows(RaabCovObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (RaabCov_ready(self) < 0 || ac_nargs("rows", nargs, 0) < 0)
        return NULL;
    ct_raab_cov_rows(&self->c, self->Bv, self->Jv);
    Py_RETURN_NONE;
}

/* publish(rel) -> bool (False: nothing changed, the reference publishes) */
static PyObject *RaabCov_publish(RaabCovObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double rel;
    if (RaabCov_ready(self) < 0 || ac_nargs("publish", nargs, 1) < 0 || ac_double(args[0], &rel) < 0)
        return NULL;
    if (ct_raab_cov_publish(&self->c, self->x, self->R, self->w, self->cur, self->pm, rel))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef RaabCov_methods[] = {
    {"rows", (PyCFunction)(void (*)(void))RaabCov_rows, METH_FASTCALL,
     "rows(): as RaabCovariance.rows of the bound fields and gradients"},
    {"publish", (PyCFunction)(void (*)(void))RaabCov_publish, METH_FASTCALL,
     "publish(rel) -> bool: as RaabCovariance.publish on the bound buffers; False where the reference must run"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RaabCovType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.RaabCov",
    .tp_basicsize = sizeof(RaabCovObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Raab's covariance buffers bound for ct_raab_cov_rows / ct_raab_cov_publish (pose.raab_covariance)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RaabCov_init,
    .tp_dealloc = (destructor)RaabCov_dealloc,
    .tp_methods = RaabCov_methods,
};

/* ----------------------------------------------------------------- RaabIO */
enum { RI_CBAR, RI_SV, RI_WV, RI_CUR, RI_SRMS, RI_HEMI, RI_M9, RI_R, RI_X, RI_MPA, RI_MOM, RI_MP, RI_SC, RI_POS,
       RI_ROT, RI_ANG, RI_PM, RI_ACQ, RI_NBUF };

typedef struct {
    PyObject_HEAD
    struct ct_raab_io in;
    Py_buffer views[RI_NBUF];
    int nbound;
} RaabIOObject;

static void RaabIO_release(RaabIOObject *self)
{
    int i;
    for (i = 0; i < self->nbound; ++i)
        PyBuffer_Release(&self->views[i]);
    self->nbound = 0;
}

static void RaabIO_dealloc(RaabIOObject *self)
{
    RaabIO_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* RaabIO(n, tol, c_raab, margin, bufs): bufs the 18 arrays cbar, Sv, wv, cur, sigma_rms, hemi, m9, R, x, mpa,
 * mom, mp, Sc, position, rotation, angles, pm, acq_hemi */
static int RaabIO_init(RaabIOObject *self, PyObject *args, PyObject *kw)
{
    static char *kwlist[] = {"n", "tol", "c_raab", "margin", "bufs", NULL};
    static const char *names[RI_NBUF] = {"cbar", "Sv", "wv", "cur", "sigma_rms", "hemi", "m9", "R", "x", "mpa",
                                         "mom", "mp", "Sc", "position", "rotation", "angles", "pm", "acq_hemi"};
    int n, i;
    double tol, c_raab, margin;
    PyObject *bufs;
    Py_ssize_t want[RI_NBUF];
    if (!PyArg_ParseTupleAndKeywords(args, kw, "idddO", kwlist, &n, &tol, &c_raab, &margin, &bufs))
        return -1;
    if (self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: already bound");
        return -1;
    }
    if (n < 3 || n > 64) {
        PyErr_SetString(PyExc_ValueError, "RaabIO: n in 3..64");
        return -1;
    }
    if (!PyTuple_Check(bufs) || PyTuple_GET_SIZE(bufs) != RI_NBUF) {
        PyErr_Format(PyExc_TypeError, "RaabIO: bufs must be a tuple of %d arrays", RI_NBUF);
        return -1;
    }
    want[RI_CBAR] = 3; want[RI_SV] = want[RI_WV] = 3 * n; want[RI_CUR] = n; want[RI_SRMS] = 1; want[RI_HEMI] = 3;
    want[RI_M9] = want[RI_R] = 9; want[RI_X] = 6; want[RI_MPA] = want[RI_MOM] = want[RI_MP] = 3 * n;
    want[RI_SC] = 3 * n; want[RI_POS] = 3; want[RI_ROT] = 9; want[RI_ANG] = 6; want[RI_PM] = want[RI_ACQ] = 3;
    for (i = 0; i < RI_NBUF; ++i) {
        int ro = i == RI_CBAR || i == RI_MPA || i == RI_SC || i == RI_PM || i == RI_ACQ;
        if (ac_buffer(PyTuple_GET_ITEM(bufs, i), want[i], F64, !ro, &self->views[i], names[i]) < 0) {
            RaabIO_release(self);
            return -1;
        }
        self->nbound = i + 1;
    }
#define DBUF(i) ((double *)self->views[i].buf)
    self->in.n = n;
    self->in.tol = tol;
    self->in.cbar = DBUF(RI_CBAR); self->in.Sv = DBUF(RI_SV); self->in.wv = DBUF(RI_WV); self->in.cur = DBUF(RI_CUR);
    self->in.sigma_rms = DBUF(RI_SRMS); self->in.hemi = DBUF(RI_HEMI); self->in.m9 = DBUF(RI_M9);
    self->in.R = DBUF(RI_R); self->in.x = DBUF(RI_X); self->in.mpa = DBUF(RI_MPA); self->in.mom = DBUF(RI_MOM);
    self->in.mp = DBUF(RI_MP); self->in.Sc = DBUF(RI_SC); self->in.position = DBUF(RI_POS);
    self->in.rotation = DBUF(RI_ROT); self->in.angles = DBUF(RI_ANG);
    self->in.pm = DBUF(RI_PM); self->in.acq_hemi = DBUF(RI_ACQ);
    self->in.c_raab = c_raab;
    self->in.margin = margin;
#undef DBUF
    return 0;
}

#define AC_AT(v, i) (*(const double *)((const char *)(v).buf + (i) * (v).strides[0]))
#define AC_AT2(v, i, j) (*(const double *)((const char *)(v).buf + (i) * (v).strides[0] + (j) * (v).strides[1]))

/* inputs(S, sigma, cur, hemisphere, x0_position, x0_rotation) -> int or None: ct_raab_inputs (the
 * CT_RIN_* codes) for float64 arrays (3, n), (3, n), (n,), (3,) or None, (3,) or None, (3, 3) or None;
 * None for inputs of another kind (the Python reference takes them) */
static PyObject *RaabIO_inputs(RaabIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer vs, vg, vc, vh, vp, vr;
    int n = self->in.n, r, have_h, have_p, have_r, i, j;
    double h[3], p[3], m[9];
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: not bound");
        return NULL;
    }
    if (ac_nargs("inputs", nargs, 6) < 0)
        return NULL;
    have_h = args[3] != Py_None;
    have_p = args[4] != Py_None;
    have_r = args[5] != Py_None;
    if (!ct_py_view(args[0], &vs, 3, n))
        Py_RETURN_NONE;
    if (!ct_py_view(args[1], &vg, 3, n)) {
        PyBuffer_Release(&vs);
        Py_RETURN_NONE;
    }
    if (vs.strides[0] != vg.strides[0] || vs.strides[1] != vg.strides[1] || !ct_py_view(args[2], &vc, n, 0)) {
        PyBuffer_Release(&vs);
        PyBuffer_Release(&vg);
        Py_RETURN_NONE;
    }
    r = 1;
    if (have_h) {
        if (ct_py_view(args[3], &vh, 3, 0)) {
            for (i = 0; i < 3; ++i)
                h[i] = AC_AT(vh, i);
            PyBuffer_Release(&vh);
        } else
            r = 0;
    }
    if (r && have_p) {
        if (ct_py_view(args[4], &vp, 3, 0)) {
            for (i = 0; i < 3; ++i)
                p[i] = AC_AT(vp, i);
            PyBuffer_Release(&vp);
        } else
            r = 0;
    }
    if (r && have_r) {
        if (ct_py_view(args[5], &vr, 3, 3)) {
            for (i = 0; i < 3; ++i)
                for (j = 0; j < 3; ++j)
                    m[3 * i + j] = AC_AT2(vr, i, j);
            PyBuffer_Release(&vr);
        } else
            r = 0;
    }
    if (r)
        r = ct_raab_inputs(&self->in, (const double *)vs.buf, (const double *)vg.buf, vs.strides[0] / 8,
                           vs.strides[1] / 8, (const double *)vc.buf, vc.strides[0] / 8, have_h ? h : NULL,
                           have_p && have_r ? p : NULL, have_p && have_r ? m : NULL, have_p == have_r);
    else
        r = -1;
    PyBuffer_Release(&vs);
    PyBuffer_Release(&vg);
    PyBuffer_Release(&vc);
    if (r < 0)
        Py_RETURN_NONE;
    return PyLong_FromLong(r);
}
#undef AC_AT
#undef AC_AT2

/* residual_cost() -> float: ct_raab_residual_cost over the bound buffers */
static PyObject *RaabIO_residual_cost(RaabIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: not bound");
        return NULL;
    }
    if (ac_nargs("residual_cost", nargs, 0) < 0)
        return NULL;
    return PyFloat_FromDouble(ct_raab_residual_cost(&self->in));
}

/* finish_pose() -> bool: ct_raab_finish_pose (False: the position is not finite) */
static PyObject *RaabIO_finish_pose(RaabIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)args;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: not bound");
        return NULL;
    }
    if (ac_nargs("finish_pose", nargs, 0) < 0)
        return NULL;
    if (ct_raab_finish_pose(&self->in))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* moved(refresh) -> bool: ct_raab_moved */
static PyObject *RaabIO_moved(RaabIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    double refresh;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: not bound");
        return NULL;
    }
    if (ac_nargs("moved", nargs, 1) < 0 || ac_double(args[0], &refresh) < 0)
        return NULL;
    if (ct_raab_moved(&self->in, refresh))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* behind(acquiring) -> bool: ct_raab_behind */
static PyObject *RaabIO_behind(RaabIOObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    int acquiring;
    if (!self->nbound) {
        PyErr_SetString(PyExc_RuntimeError, "RaabIO: not bound");
        return NULL;
    }
    if (ac_nargs("behind", nargs, 1) < 0 || (acquiring = PyObject_IsTrue(args[0])) < 0)
        return NULL;
    if (ct_raab_behind(&self->in, acquiring))
        Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

static PyMethodDef RaabIO_methods[] = {
    {"moved", (PyCFunction)(void (*)(void))RaabIO_moved, METH_FASTCALL, "moved(refresh) -> bool: as RaabIO.moved"},
    {"behind", (PyCFunction)(void (*)(void))RaabIO_behind, METH_FASTCALL,
     "behind(acquiring) -> bool: as RaabIO.behind"},
    {"residual_cost", (PyCFunction)(void (*)(void))RaabIO_residual_cost, METH_FASTCALL,
     "residual_cost() -> float: as raab_update.residual_cost of the bound buffers"},
    {"finish_pose", (PyCFunction)(void (*)(void))RaabIO_finish_pose, METH_FASTCALL,
     "finish_pose() -> bool: RaabTracker._finish's pose into the bound results"},
    {"inputs", (PyCFunction)(void (*)(void))RaabIO_inputs, METH_FASTCALL,
     "inputs(S, sigma, cur, hemisphere, x0_position, x0_rotation) -> int or None: as RaabIO.load"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject RaabIOType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "coiltrack.firmware._core.RaabIO",
    .tp_basicsize = sizeof(RaabIOObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Raab's tracker's inputs and results bound for ct_raab_inputs and the others of pose.raab_io",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RaabIO_init,
    .tp_dealloc = (destructor)RaabIO_dealloc,
    .tp_methods = RaabIO_methods,
};

/* ------------------------------------------------------------------ module */
int ct_register_ac(PyObject *m)
{
    if (PyType_Ready(&DemodType) < 0 || PyType_Ready(&RaabType) < 0 || PyType_Ready(&RaabCorrType) < 0 ||
        PyType_Ready(&RaabCovType) < 0 || PyType_Ready(&RaabIOType) < 0 || PyType_Ready(&ACBlocksType) < 0)
        return -1;
    Py_INCREF(&ACBlocksType);
    if (PyModule_AddObject(m, "ACBlocks", (PyObject *)&ACBlocksType) < 0) {
        Py_DECREF(&ACBlocksType);
        return -1;
    }
    Py_INCREF(&DemodType);
    if (PyModule_AddObject(m, "Demod", (PyObject *)&DemodType) < 0) {
        Py_DECREF(&DemodType);
        return -1;
    }
    Py_INCREF(&RaabType);
    if (PyModule_AddObject(m, "Raab", (PyObject *)&RaabType) < 0) {
        Py_DECREF(&RaabType);
        return -1;
    }
    Py_INCREF(&RaabCorrType);
    if (PyModule_AddObject(m, "RaabCorr", (PyObject *)&RaabCorrType) < 0) {
        Py_DECREF(&RaabCorrType);
        return -1;
    }
    Py_INCREF(&RaabCovType);
    if (PyModule_AddObject(m, "RaabCov", (PyObject *)&RaabCovType) < 0) {
        Py_DECREF(&RaabCovType);
        return -1;
    }
    Py_INCREF(&RaabIOType);
    if (PyModule_AddObject(m, "RaabIO", (PyObject *)&RaabIOType) < 0) {
        Py_DECREF(&RaabIOType);
        return -1;
    }
    if (PyModule_AddIntConstant(m, "DM_NST", CT_DM_NST) < 0 || PyModule_AddIntConstant(m, "DMO_N", CT_DMO_N) < 0)
        return -1;
    return 0;
}
