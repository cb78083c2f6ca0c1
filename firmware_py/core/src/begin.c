/*
 * A burst's solve inputs at its begin: see include/ct_begin.h.  The same operations as the Python
 * named beside each function (tests/firmware/core/test_core_begin.py).
 */
#include <string.h>

#include "coiltrack_core.h"

/* track/status.py input_status */
int64_t ct_input_status(const struct ct_begin_bits *b, int64_t window_flags, int64_t coil_faults)
{
    int64_t bits = 0;
    if (window_flags & b->pulse_saturated)
        bits |= b->pose_saturated;
    if (window_flags)
        bits |= b->pose_degraded;
    if (coil_faults)
        bits |= b->pose_coil_fault;
    return bits;
}

/* MagneticTracker._begin's inputs (SensorChannel.burst_flags, PulseSchedule.any_faults) */
int64_t ct_begin_inputs(const struct ct_begin_bits *b, const int64_t *fl, int nf, const int64_t *fv, int nc,
                        int64_t *flags, int *unusable)
{
    int64_t f = 0, faults = 0;
    int j;
    for (j = 0; j < nf; ++j)
        f |= fl[j];
    for (j = 0; j < nc; ++j)
        faults |= fv[j];
    *flags = f;
    *unusable = (f & b->pulse_unusable) != 0 || (faults & b->coil_fatal) != 0;
    return ct_input_status(b, f, faults);
}

/* MagneticTracker._prepare_currents */
void ct_prepare_currents(const double *measured, const double *nominal, double *cur, int n)
{
    int j;
    for (j = 0; j < n; ++j)
        cur[j] = measured[j] != 0.0 ? measured[j] : nominal[j];
}

/* MagneticTracker._start_solve (BurstFusionTracker's warm start, no solve ahead taken over) */
int ct_solve_start(const struct ct_solve *s, int n, const double *var, double *sig, double floor2,
                   const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                   const double *tp, const double *tR, double *wp, double *wR, const double *hemi, const double *S,
                   const double *cur, int *warm)
{
    ct_sigma_from(3 * (int64_t)n, var, sig, floor2);
    *warm = ct_report_warm_start(h, t_ref, have_pose, initialized, range_m, tp, tR, wp, wR);
    if (*warm)
        return ct_solve_begin(s, S, sig, n, 1, cur, 1, tp, wp, wR);
    return ct_solve_begin(s, S, sig, n, 1, cur, 1, hemi, NULL, NULL);
}
