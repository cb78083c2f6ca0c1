/*
 * The CPython glue of a pulse window (py_window.c PulseWindow, py_multi.c WindowColumn): the
 * magnetometer's sample ring and the pulse extractor bound to the caller's arrays, as
 * measure.pulse.SampleRing and PulseExtractor hold them. Static inline, as py_glue.h's helpers.
 */
#ifndef CT_PY_PULSE_H
#define CT_PY_PULSE_H

#include "coiltrack_core.h"
#include "py_glue.h"

/* the ring over views v[0..2] (t, b, flags; cap slots, empty) and the extractor's record over v[3..4]
 * (used_t, emp_var) with its settings: st = settle_us, fall_us, baseline_us, guard_us, min_pulse,
 * min_base, max_gap_us, max_samples; fl = drift_limit, sigma, drift_nsigma */
static inline void ct_py_pulse_bind(struct ct_sample_ring *r, struct ct_pulse *x, const Py_buffer *v,
                                    Py_ssize_t cap, const long long *st, const double *fl)
{
    r->t = (const int64_t *)v[0].buf;
    r->b = (const double *)v[1].buf;
    r->flags = (const uint8_t *)v[2].buf;
    r->cap = (int64_t)cap;
    r->head = 0;
    r->count = 0;
    x->used_t = (int64_t *)v[3].buf;
    x->emp_var = (double *)v[4].buf;
    x->settle_us = st[0];
    x->fall_us = st[1];
    x->baseline_us = st[2];
    x->guard_us = st[3];
    x->min_pulse = st[4];
    x->min_base = st[5];
    x->max_gap_us = st[6];
    x->max_samples = st[7];
    x->drift_limit = fl[0];
    x->sigma = fl[1];
    x->drift_nsigma = fl[2];
}

/* o's extractor, ring (its head and count as of o's last call), result buffers res (6) and ires (4)
 * (py_window.c), or -1 with a TypeError when o is no bound PulseWindow */
int ct_py_pulse_window_of(PyObject *o, const struct ct_pulse **x, const struct ct_sample_ring **r, double **res,
                          int64_t **ires);

#endif /* CT_PY_PULSE_H */
