/*
 * The bound kernels' state behind the glue objects the single-coil window update (py_sc_close.c,
 * ScWindowUpdate) runs in one call: SchepersCore and SingleCoilUpdateCore (py_single_coil.c),
 * ScUpdateCore and SharedBaselinesCore (py_sc_window.c).  The callers check the objects once (the
 * *_ready and *_state functions) when they bind them.
 */
#ifndef CT_PY_SC_CLOSE_H
#define CT_PY_SC_CLOSE_H

#include <Python.h>
#include <stdint.h>

struct ct_sc;

/* py_single_coil.c: a bound SchepersCore's state (NULL: not one); whether o is a SingleCoilUpdateCore of
 * nx states with its run bound; its run (SingleCoilUpdateCore.run without a coil gain, its outputs in out);
 * its bound model's coils */
struct ct_sc *ct_py_sc_state(PyObject *o);
int ct_py_scu_ready(PyObject *o, int nx);
struct ct_py_scu_out {
    int64_t applied, rejected;         /* the shared update's applied and rejected passes */
    double nis, nis_last, evals;       /* the first pass's NIS, the last one's; the model's evaluations */
    double nis_nominal;                /* the first pass's NIS with r_scale 1 */
    const double *dx;                  /* the error estimate (nx) */
};
int ct_py_scu_run(PyObject *o, double *P, const double *p, const double *R, long cp, long co, long coil,
                  const double *y, const double *var, double current, double rel_model, double r_scale, double gate,
                  long iters, long long count, struct ct_py_scu_out *out);
int ct_py_scu_coils(PyObject *o);

/* py_sc_window.c: whether o is a bound ScUpdateCore; its clones; its prior (k < its clones) and after
 * (linear: the prior's flag); its NIS monitor's state (CT_NIS_NST); a SharedBaselinesCore's bound
 * channels (-1: not one) and channel k's variance (k below them) */
int ct_py_scw_ready(PyObject *o);
int64_t ct_py_scw_clones(PyObject *o);
double ct_py_scw_prior(PyObject *o, int64_t k, double current);
double ct_py_scw_after(PyObject *o, double nis_nominal, double nis, int *linear);
const double *ct_py_scw_monitor_state(PyObject *o);
int ct_py_sb_channels(PyObject *o);
const double *ct_py_sb_variance(PyObject *o, int64_t k);

#endif /* CT_PY_SC_CLOSE_H */
