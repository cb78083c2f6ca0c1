/*
 * The single-coil window close's shared baselines (estimate/shared_baseline.py) in C99: which
 * sides of a closed pulse window share their baseline samples with a neighbouring pulse, and the
 * variance its amplitude then carries (Schepers & Veltink 2010, seeds/000_e46ec0e8bf7ea271.txt
 * sec. 3.1, sigma/sqrt(n); thesis seeds/002_cd7f1fdb7fc67471.txt sec. 5.4; the bound in the
 * module docstring of shared_baseline.py).  The Python is the reference: the same names (ct_
 * prefix: span_overlap, SharedBaselines.before_after, close, shared_variance, variance), the same
 * scalar operations in the same order, so the same bits.  Times are integer microseconds
 * (|t| < 2^53: every int -> double conversion exact, as Python's int / int and int * float are).
 * The state lives in two caller-owned arrays (the reference's attributes).
 */
#ifndef CT_SC_WINDOW_H
#define CT_SC_WINDOW_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* si[]: the integers (SharedBaselines' fall_us, baseline_us, guard_us, enabled, whether a
 * window was closed before (prev_end not None), prev_end, _start, _end, _b0, _b1, _a0, _a1,
 * n_base, apart) */
enum { CT_SB_FALL, CT_SB_BASE, CT_SB_GUARD, CT_SB_ENABLED, CT_SB_HAS_PREV, CT_SB_PREV_END,
       CT_SB_START, CT_SB_END, CT_SB_B0, CT_SB_B1, CT_SB_A0, CT_SB_A1, CT_SB_NBASE, CT_SB_APART, CT_SB_NI };
/* sf[]: the floats (sigma2, period_us, shared, fb, fa) */
enum { CT_SB_SIGMA2, CT_SB_PERIOD, CT_SB_SHARED, CT_SB_FB, CT_SB_FA, CT_SB_NF };

/* the open end of an after side that any later pulse may share (the reference's 1 << 62) */
#define CT_SB_FAR ((int64_t)1 << 62)

double ct_span_overlap(int64_t a0, int64_t a1, int64_t b0, int64_t b1);
void ct_sb_before_after(const int64_t *si, int64_t start, int64_t end, int has_prev, int64_t prev_end,
                        int64_t next_start, double *fb, double *fa);
double ct_sb_close(int64_t *si, double *sf, int64_t start, int64_t end, int64_t next_start, int64_t earliest_next_us);
double ct_sb_shared_variance(const int64_t *si, const double *sf, int64_t n_used, int64_t n_base, int64_t first_us,
                             int64_t last_us);
void ct_sb_variance(const int64_t *si, const double *sf, const double *amp_var, const int64_t *info, double *var);
/* SharedBaselines.predicted (a decision's variance of a pulse starting at start, the previous one
 * ending at prev_end, 0 or less: none) and chained (a pulse in flight's) */
double ct_sb_predicted(const int64_t *si, const double *sf, double var_amp, int64_t start, int64_t prev_end);
double ct_sb_chained(const int64_t *si, const double *sf, double var_amp);

/* The single-coil window update's Python around the one-call update (track/single_coil_tracker.py,
 * SingleCoilTracker._update and its reference helpers window_prior, window_after).
 *
 * ct_scw_prior: the prior's test of the NIS's linearisation and the measurement's relative error.
 * P the filter's covariance (nP x nP, row-major), pos the first position row, p the position the
 * update linearises at (the clone's or the state's, 3); sp2 = max of P's three position variances
 * (Python's max: the first of equal values), linear = sp2 < lin2 |p|^2; returns
 * rel = sqrt(rel2 + (tol_a / max(|current|, 1e-6))^2) and *linear. */
double ct_scw_prior(const double *P, int64_t nP, int64_t pos, const double *p, double lin2, double rel2,
                    double tol_a, double current, int *linear);

/* ct_scw_after: PoseQuality.consistency(node, 0.0, nis / 3.0) with the quality's fit term 0 (no
 * residual freedom: dof 0) and its quiet term of the sensor's magnetometer ring (ct_report_quiet;
 * have_quiet 0: the term off, 0.0), returned; then, when linear, the NIS monitor's add(nis_nominal)
 * and add_used(nis) (ct_nis_add, ct_nis_add_used), in the reference's order. */
struct ct_nis;
double ct_scw_after(struct ct_nis *mon, const int64_t *hc, const double *b, int64_t cap, int have_quiet,
                    double earth, double quiet_sigma, double nis_nominal, double nis, int linear);

#ifdef __cplusplus
}
#endif

#endif /* CT_SC_WINDOW_H */
