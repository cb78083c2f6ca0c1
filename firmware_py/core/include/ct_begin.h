/*
 * A burst's solve inputs at its begin (compiled core): the or of a channel's window flags and of the
 * coil driver's faults with the POSE bits they give, and the burst's currents.
 *
 * Reference (the Python is the specification, followed operation by operation, same names with the
 * ct_ prefix): track/magnetic.py MagneticTracker._begin's first lines (measure/windows.py
 * SensorChannel.burst_flags, actuate/schedule.py PulseSchedule.any_faults, track/status.py
 * input_status, the usable test without the supervisor's veto) and MagneticTracker._prepare_currents.
 */
#ifndef CT_BEGIN_H
#define CT_BEGIN_H

#include <stdint.h>

/* the masks and bits of the Python constants (given at binding): the window flag of a saturated
 * window, the flags and faults that make a burst unusable, POSE_SATURATED, POSE_DEGRADED,
 * POSE_COIL_FAULT */
struct ct_begin_bits {
    int64_t pulse_saturated, pulse_unusable, coil_fatal, pose_saturated, pose_degraded, pose_coil_fault;
};

/* input_status(window_flags, coil_faults) */
int64_t ct_input_status(const struct ct_begin_bits *b, int64_t window_flags, int64_t coil_faults);
/* _begin's inputs: flags = or of fl (nf), faults = or of fv (nc); returns input_status's bits, with
 * *flags and *unusable (the flags' or the faults' part of the usable test) */
int64_t ct_begin_inputs(const struct ct_begin_bits *b, const int64_t *fl, int nf, const int64_t *fv, int nc,
                        int64_t *flags, int *unusable);
/* _prepare_currents: cur[j] = measured[j] where the driver reported one (non-zero), else nominal[j] */
void ct_prepare_currents(const double *measured, const double *nominal, double *cur, int n);

struct ct_solve;
struct ct_hist;
/* MagneticTracker._start_solve of BurstFusionTracker (no solve ahead to take over): the channel's
 * sigma from its variances (SensorChannel.fill_sigma: ct_sigma_from over var, 3n, into sig with the
 * floor floor2), the warm start (BurstFusionTracker.warm_start: ct_report_warm_start over the fusion
 * filter's live history h at t_ref into wp, wR, from the tracked pose tp, tR) and the solve's begin
 * (PoseSolver.begin: ct_solve_begin on S, sig, cur; warm: the hemisphere tp with the start wp, wR,
 * else the hemisphere hemi).  range_check 0: ACFusionTracker.warm_start's (ct_report_warm_start_ac: no
 * range check, range_m unused).  Returns the begin's status, *warm whether a warm start was made. */
int ct_solve_start(const struct ct_solve *s, int n, const double *var, double *sig, double floor2,
                   const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                   const double *tp, const double *tR, double *wp, double *wR, const double *hemi, const double *S,
                   const double *cur, int range_check, int *warm);

struct ct_pulse;
struct ct_sample_ring;
/* one sensor's _Ahead (track/magnetic.py): its copies of a burst's inputs, S, sigma (3 x n, row-major),
 * currents (n), hemisphere (3), warm_p (3), warm_R (9), its last window's amp, var (3 each), and warm
 * (1: _Ahead.wst, whether its solve began warm, 1, or acquiring, 0) */
struct ct_ahead_buf {
    double *S, *sigma, *cur, *hemi, *wp, *wR, *amp, *var;
    int64_t *warm;
};
/* MagneticTracker._begin_ahead: the last window (coil n - 1, [start, end]) extracted on the channel's
 * ring r (PulseExtractor.extract: ct_pulse_extract into res (6) and ires (4), then amp and var), and,
 * where it has pulse and baseline samples, the channel's S and var (3 x n) copied with that column
 * replaced, the sigma from them in place (floor2), the currents prepared (measured, nominal), the
 * start's kind recorded (ah->warm: wp given), the hemisphere hemi and, warm, the start wp, wR copied and
 * the solve begun on the copies (warm, or acquiring where wp is NULL).  Returns the begin's status, or
 * CT_AHEAD_NO_WINDOW. */
int ct_begin_ahead(const struct ct_solve *s, int n, const struct ct_pulse *x, const struct ct_sample_ring *r,
                   int64_t start, int64_t end, double *res, int64_t *ires, const double *S, const double *var,
                   double floor2, const double *measured, const double *nominal, const double *hemi, const double *wp,
                   const double *wR, const struct ct_ahead_buf *ah);
/* MagneticTracker._ahead_start of BurstFusionTracker: its warm start (ct_report_warm_start, as in
 * ct_solve_start), then ct_begin_ahead from it (the hemisphere tp) or, where it made none, acquiring
 * from the sensor's hemisphere hemi.  Returns the begin's status | warm << 8, or CT_AHEAD_NO_WINDOW. */
int ct_ahead_start(const struct ct_solve *s, int n, const struct ct_hist *h, int64_t t_ref, int have_pose,
                   int initialized, double range_m, const double *tp, const double *tR, double *wp, double *wR,
                   const double *hemi, const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t start,
                   int64_t end, double *res, int64_t *ires, const double *S, const double *var, double floor2,
                   const double *measured, const double *nominal, const struct ct_ahead_buf *ah);
enum { CT_AHEAD_NO_WINDOW = -2 };
/* MagneticTracker._start_solve of BurstFusionTracker where a solve ahead may be taken over, up to
 * _use_ahead's comparison: the sigma (ct_sigma_from over var into sig, as in ct_solve_start), the warm
 * start (ct_report_warm_start into wp, wR), then whether the solve ahead began from the same kind of
 * start (ah->warm) and, where it did, _Ahead.same of the burst's inputs against its copies in ah
 * (ct_report_same; warm: S, sig, cur, the hemisphere tp, wp, wR; acquiring: S, sig, cur and the
 * sensor's hemisphere hemi).  Returns warm | same << 1. */
int ct_ahead_inputs(int n, const double *var, double *sig, double floor2, const struct ct_hist *h, int64_t t_ref,
                    int have_pose, int initialized, double range_m, const double *tp, const double *tR, double *wp,
                    double *wR, const double *hemi, const double *S, const double *cur,
                    const struct ct_ahead_buf *ah);

struct ct_sup;
/* MagneticTracker._begin_handover's first steps (_begin on the compiled core): ct_begin_inputs of the
 * channel's window flags fl (nf) and the faults fv (nc), then Supervisor.pose_status of node with those
 * flags (ct_sup_pose_status on sup).  Returns the burst's POSE bits (input_status's | pose_status's, 32
 * bits) | veto << 32 | unusable << 33, or -1 where input_status's bits or the flags are out of range
 * (nothing written: nothing is). */
int64_t ct_handover_status(const struct ct_begin_bits *b, const int64_t *fl, int nf, const int64_t *fv, int nc,
                           const struct ct_sup *sup, int64_t node);
/* MagneticTracker._start_solve_compiled's test for a solve ahead to take over: its record st (burst,
 * done) is of burst and done, or it is the solve running (running == k) */
int ct_handover_ahead(const int64_t *st, int64_t burst, int64_t running, int64_t k);

#endif /* CT_BEGIN_H */
