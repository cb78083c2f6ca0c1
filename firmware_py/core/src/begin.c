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

/* MagneticTracker._start_solve (BurstFusionTracker's warm start or, range_check 0, ACFusionTracker's; no solve
 * ahead taken over) */
int ct_solve_start(const struct ct_solve *s, int n, const double *var, double *sig, double floor2,
                   const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                   const double *tp, const double *tR, double *wp, double *wR, const double *hemi, const double *S,
                   const double *cur, int range_check, int *warm)
{
    ct_sigma_from(3 * (int64_t)n, var, sig, floor2);
    *warm = range_check ? ct_report_warm_start(h, t_ref, have_pose, initialized, range_m, tp, tR, wp, wR)
                        : ct_report_warm_start_ac(h, t_ref, have_pose, initialized, tp, tR, wp, wR);
    if (*warm)
        return ct_solve_begin(s, S, sig, n, 1, cur, 1, tp, wp, wR);
    return ct_solve_begin(s, S, sig, n, 1, cur, 1, hemi, NULL, NULL);
}

/* MagneticTracker._begin_ahead (its extract: PulseExtractor._extract_compiled over ct_pulse_extract) */
int ct_begin_ahead(const struct ct_solve *s, int n, const struct ct_pulse *x, const struct ct_sample_ring *r,
                   int64_t start, int64_t end, double *res, int64_t *ires, const double *S, const double *var,
                   double floor2, const double *measured, const double *nominal, const double *hemi, const double *wp,
                   const double *wR, const struct ct_ahead_buf *ah)
{
    int i, j = n - 1;
    ct_pulse_extract(x, r, start, end, res, res + 3, ires);
    for (i = 0; i < 3; ++i) {
        ah->amp[i] = res[i];
        ah->var[i] = res[3 + i];
    }
    if (ires[1] == 0 || ires[2] == 0)
        return CT_AHEAD_NO_WINDOW;
    memcpy(ah->S, S, sizeof(double) * 3 * (size_t)n);
    memcpy(ah->sigma, var, sizeof(double) * 3 * (size_t)n);
    for (i = 0; i < 3; ++i) {
        ah->S[i * n + j] = ah->amp[i];
        ah->sigma[i * n + j] = ah->var[i];
    }
    ct_sigma_from(3 * (int64_t)n, ah->sigma, ah->sigma, floor2);
    ct_prepare_currents(measured, nominal, ah->cur, n);
    ah->warm[0] = wp != NULL;
    memcpy(ah->hemi, hemi, sizeof(double) * 3);
    if (wp == NULL)
        return ct_solve_begin(s, ah->S, ah->sigma, n, 1, ah->cur, 1, ah->hemi, NULL, NULL);
    memcpy(ah->wp, wp, sizeof(double) * 3);
    memcpy(ah->wR, wR, sizeof(double) * 9);
    return ct_solve_begin(s, ah->S, ah->sigma, n, 1, ah->cur, 1, ah->hemi, ah->wp, ah->wR);
}

/* MagneticTracker._ahead_start (BurstFusionTracker.warm_start, then _begin_ahead, warm or acquiring) */
int ct_ahead_start(const struct ct_solve *s, int n, const struct ct_hist *h, int64_t t_ref, int have_pose,
                   int initialized, double range_m, const double *tp, const double *tR, double *wp, double *wR,
                   const double *hemi, const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t start,
                   int64_t end, double *res, int64_t *ires, const double *S, const double *var, double floor2,
                   const double *measured, const double *nominal, const struct ct_ahead_buf *ah)
{
    int warm = ct_report_warm_start(h, t_ref, have_pose, initialized, range_m, tp, tR, wp, wR) != 0;
    int st = ct_begin_ahead(s, n, x, r, start, end, res, ires, S, var, floor2, measured, nominal, warm ? tp : hemi,
                            warm ? wp : NULL, wR, ah);
    return st < 0 ? st : st | warm << 8;
}

/* MagneticTracker._start_solve up to _use_ahead's comparison (fill_sigma, BurstFusionTracker.warm_start,
 * _Ahead.warm, _Ahead.same) */
int ct_ahead_inputs(int n, const double *var, double *sig, double floor2, const struct ct_hist *h, int64_t t_ref,
                    int have_pose, int initialized, double range_m, const double *tp, const double *tR, double *wp,
                    double *wR, const double *hemi, const double *S, const double *cur,
                    const struct ct_ahead_buf *ah)
{
    const double *a[6], *b[6];
    int64_t len[6];
    int warm;
    ct_sigma_from(3 * (int64_t)n, var, sig, floor2);
    warm = ct_report_warm_start(h, t_ref, have_pose, initialized, range_m, tp, tR, wp, wR) != 0;
    if (warm != (ah->warm[0] != 0))
        return warm;
    a[0] = ah->S, a[1] = ah->sigma, a[2] = ah->cur, a[3] = ah->hemi, a[4] = ah->wp, a[5] = ah->wR;
    b[0] = S, b[1] = sig, b[2] = cur, b[3] = warm ? tp : hemi, b[4] = wp, b[5] = wR;
    len[0] = len[1] = 3 * (int64_t)n, len[2] = n, len[3] = len[4] = 3, len[5] = 9;
    return warm | ct_report_same(warm ? 6 : 4, a, b, len) << 1;
}

/* MagneticTracker._begin_handover: _begin_compiled's BurstInputs.status, then the supervisor's
 * pose_status (Supervisor._pose_status_compiled) */
int64_t ct_handover_status(const struct ct_begin_bits *b, const int64_t *fl, int nf, const int64_t *fv, int nc,
                           const struct ct_sup *sup, int64_t node)
{
    int64_t flags, bits, ps;
    int unusable;
    bits = ct_begin_inputs(b, fl, nf, fv, nc, &flags, &unusable);
    if (bits < 0 || bits > 255 || flags < 0)
        return -1;
    ps = ct_sup_pose_status(sup, node, flags);
    return (bits | (ps & 0xFFFFFFFF)) | (((ps >> 32) & 1) << 32) | ((int64_t)(unusable != 0) << 33);
}

/* MagneticTracker._start_solve_compiled: st[0] == burst and (st[1] or running == k) */
int ct_handover_ahead(const int64_t *st, int64_t burst, int64_t running, int64_t k)
{
    return st[0] == burst && (st[1] != 0 || running == k);
}
