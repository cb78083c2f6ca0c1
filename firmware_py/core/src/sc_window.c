/*
 * The shared baselines of the single-coil window close: estimate/shared_baseline.py's
 * span_overlap and SharedBaselines (before_after, close, shared_variance, variance), operation by
 * operation (include/ct_sc_window.h).
 */
#include <math.h>

#include "coiltrack_core.h"

/* span_overlap: the fraction of [a0, a1] covered by [b0, b1] (0 for an empty [a0, a1]) */
double ct_span_overlap(int64_t a0, int64_t a1, int64_t b0, int64_t b1)
{
    int64_t lo, hi;
    if (a1 <= a0)
        return 0.0;
    lo = a0 > b0 ? a0 : b0;
    hi = a1 < b1 ? a1 : b1;
    if (hi <= lo)
        return 0.0;
    return (double)(hi - lo) / (double)(a1 - a0);
}

/* SharedBaselines.before_after: the fractions of the pulse [start, end]'s before and after spans
 * covered by the previous pulse's after span (has_prev: prev_end given) and the next pulse's
 * before span (next_start < 0: none) */
void ct_sb_before_after(const int64_t *si, int64_t start, int64_t end, int has_prev, int64_t prev_end,
                        int64_t next_start, double *fb, double *fa)
{
    const int64_t fall = si[CT_SB_FALL], base = si[CT_SB_BASE], guard = si[CT_SB_GUARD];
    int64_t b0 = start - base, b1 = start - guard;
    int64_t a0 = end + fall, a1 = end + fall + base;
    *fb = 0.0;
    if (has_prev)
        *fb = ct_span_overlap(b0, b1, prev_end + fall, prev_end + fall + base);
    *fa = 0.0;
    if (next_start >= 0)
        *fa = ct_span_overlap(a0, a1, next_start - base, next_start - guard);
}

/* SharedBaselines.close: the window of the pulse [start, end] is being closed (next_start: the
 * next commanded pulse's start or -1; earliest_next_us: the earliest start of a pulse not yet
 * commanded, -1: none may follow); sets and returns shared (fb + fa) */
double ct_sb_close(int64_t *si, double *sf, int64_t start, int64_t end, int64_t next_start, int64_t earliest_next_us)
{
    const int64_t fall = si[CT_SB_FALL], base = si[CT_SB_BASE], guard = si[CT_SB_GUARD];
    int has_prev = si[CT_SB_HAS_PREV] != 0;
    int64_t prev = si[CT_SB_PREV_END];
    double fb, fa, unused;
    si[CT_SB_HAS_PREV] = 1;
    si[CT_SB_PREV_END] = end;
    si[CT_SB_START] = start;
    si[CT_SB_END] = end;
    si[CT_SB_B0] = 1;
    si[CT_SB_B1] = 0;
    si[CT_SB_A0] = 1;
    si[CT_SB_A1] = 0;
    if (next_start >= 0) {
        ct_sb_before_after(si, start, end, has_prev, prev, next_start, &fb, &fa);
        si[CT_SB_A0] = next_start - base;
        si[CT_SB_A1] = next_start - guard;
    } else {
        ct_sb_before_after(si, start, end, has_prev, prev, -1, &fb, &unused);
        fa = 0.0;
        if (earliest_next_us >= 0) {
            fa = ct_span_overlap(end + fall, end + fall + base, earliest_next_us - base, CT_SB_FAR);
            si[CT_SB_A0] = earliest_next_us - base;
            si[CT_SB_A1] = CT_SB_FAR;
        }
    }
    if (has_prev) {
        si[CT_SB_B0] = prev + fall;
        si[CT_SB_B1] = prev + fall + base;
    }
    if (!si[CT_SB_ENABLED])
        fb = fa = 0.0;
    sf[CT_SB_FB] = fb;
    sf[CT_SB_FA] = fa;
    sf[CT_SB_SHARED] = fb + fa;
    return sf[CT_SB_SHARED];
}

/* the baseline sample k (1, 2, ...) of a side (0: before, first_us - k T; 1: after, last_us + k T) */
static double sb_sample(int side, int64_t first_us, int64_t last_us, int64_t k, double T)
{
    return side == 0 ? (double)first_us - (double)k * T : (double)last_us + (double)k * T;
}

/* SharedBaselines.shared_variance: sigma^2 sum_shared w_j^2 of the window just closed, its
 * baseline samples put back on the grid of period T through the first and last used sample
 * times; the fraction rule when they do not give n_base samples */
double ct_sb_shared_variance(const int64_t *si, const double *sf, int64_t n_used, int64_t n_base, int64_t first_us,
                             int64_t last_us)
{
    const double T = sf[CT_SB_PERIOD], sigma2 = sf[CT_SB_SIGMA2], shared = sf[CT_SB_SHARED];
    const int64_t start = si[CT_SB_START], end = si[CT_SB_END];
    const int64_t b_lo = start - si[CT_SB_BASE], b_hi = start - si[CT_SB_GUARD];
    const int64_t a_lo = end + si[CT_SB_FALL], a_hi = end + si[CT_SB_FALL] + si[CT_SB_BASE];
    int64_t n = 0, k;
    double st = 0.0, stt = 0.0, tbar, sxx, tm, slope, acc = 0.0, t, w;
    int side;
    if (shared <= 0.0 || n_base <= 0)
        return 0.0;
    if (n_used <= 0 || last_us < first_us)
        return shared * sigma2 / (double)n_base;
    for (side = 0; side < 2; ++side) {
        for (k = 1;; ++k) {
            t = sb_sample(side, first_us, last_us, k, T);
            if ((side == 0 && t < (double)b_lo) || (side == 1 && t > (double)a_hi))
                break;
            if ((side == 0 && t <= (double)b_hi) || (side == 1 && t >= (double)a_lo)) {
                n += 1;
                st += t;
                stt += t * t;
            }
        }
    }
    if (n != n_base)
        return shared * sigma2 / (double)n_base;
    tbar = st / (double)n;
    sxx = stt - (double)n * tbar * tbar;
    tm = 0.5 * (double)(first_us + last_us);
    slope = sxx > 1e-9 * T * T ? (tm - tbar) / sxx : 0.0;
    for (side = 0; side < 2; ++side) {
        int64_t lo = side == 0 ? si[CT_SB_B0] : si[CT_SB_A0];
        int64_t hi = side == 0 ? si[CT_SB_B1] : si[CT_SB_A1];
        if (hi < lo)
            continue;
        for (k = 1;; ++k) {
            int inside;
            t = sb_sample(side, first_us, last_us, k, T);
            if ((side == 0 && t < (double)b_lo) || (side == 1 && t > (double)a_hi))
                break;
            inside = (side == 0 && t <= (double)b_hi) || (side == 1 && t >= (double)a_lo);
            if (inside && (double)lo <= t && t <= (double)hi) {
                w = 1.0 / (double)n + slope * (t - tbar);
                acc += w * w;
            }
        }
    }
    return sigma2 * acc;
}

/* SharedBaselines.variance: amp_var (3) plus the shared samples' part (info: the window's
 * n_used, n_base, first and last used sample times) into var (3) */
void ct_sb_variance(const int64_t *si, const double *sf, const double *amp_var, const int64_t *info, double *var)
{
    double extra = ct_sb_shared_variance(si, sf, info[0], info[1], info[2], info[3]);
    var[0] = amp_var[0] + extra;
    var[1] = amp_var[1] + extra;
    var[2] = amp_var[2] + extra;
}

/* SharedBaselines.predicted: the variance a pulse starting at start will be taken with (nominal
 * n_base, sides even): its before side as the previous pulse (ending at prev_end; 0 or less: none)
 * leaves it, its after side shared (not when pulses are kept apart) */
double ct_sb_predicted(const int64_t *si, const double *sf, double var_amp, int64_t start, int64_t prev_end)
{
    const int64_t fall = si[CT_SB_FALL], base = si[CT_SB_BASE], guard = si[CT_SB_GUARD];
    double fb = 0.0;
    if (!si[CT_SB_ENABLED])
        return var_amp;
    if (prev_end > 0)
        fb = ct_span_overlap(start - base, start - guard, prev_end + fall, prev_end + fall + base);
    return var_amp + (fb + (si[CT_SB_APART] ? 0.0 : 1.0)) * sf[CT_SB_SIGMA2] / (2.0 * (double)si[CT_SB_NBASE]);
}

/* SharedBaselines.chained: a pulse in flight's variance as a decision predicts it, both sides
 * shared (none when pulses are kept apart) */
double ct_sb_chained(const int64_t *si, const double *sf, double var_amp)
{
    return si[CT_SB_ENABLED] && !si[CT_SB_APART] ? var_amp + sf[CT_SB_SIGMA2] / (double)si[CT_SB_NBASE] : var_amp;
}

/* SingleCoilTracker._update's prior (window_prior): whether the NIS tests the linearised model (the
 * largest prior position variance small against the squared range) and the predicted field's
 * relative error (the model's and the current's) */
double ct_scw_prior(const double *P, int64_t nP, int64_t pos, const double *p, double lin2, double rel2,
                    double tol_a, double current, int *linear)
{
    int64_t d = nP + 1, b = pos * d;
    double sp2 = P[b], x = p[0], y = p[1], z = p[2], r2, a, rc;
    if (P[b + d] > sp2)
        sp2 = P[b + d];
    if (P[b + 2 * d] > sp2)
        sp2 = P[b + 2 * d];
    r2 = x * x + y * y + z * z;
    *linear = sp2 < lin2 * r2;
    a = fabs(current);
    if (1e-6 > a)
        a = 1e-6;
    rc = tol_a / a;
    return sqrt(rel2 + rc * rc);
}

/* the update's consistency term and the NIS monitor's record of it (window_after) */
double ct_scw_after(struct ct_nis *mon, const int64_t *hc, const double *b, int64_t cap, int have_quiet,
                    double earth, double quiet_sigma, double nis_nominal, double nis, int linear)
{
    double q = have_quiet ? ct_report_quiet(hc, b, cap, earth, quiet_sigma) : 0.0;
    double x = 0.0 + nis / 3.0 + q;
    if (linear) {
        ct_nis_add(mon, nis_nominal);
        ct_nis_add_used(mon, nis);
    }
    return x;
}
