/*
 * The adaptive single-coil policy's numeric parts (Schepers & Veltink 2010,
 * seeds/000_e46ec0e8bf7ea271.txt sec. 2.1 and Fig. 1) in C99: the compiled form of
 * coiltrack.firmware.actuate.accuracy (FixedCycleReference._propagate, with
 * accuracy_budget.MeanBudgetReference._propagate's running mean of the live filter's variances),
 * coil_choice.PoseCovUpdate.apply (the eq-4 covariance update of a pulse in flight) and the
 * magnetometer-range limits of single_coil_policy.AdaptiveActuation._decide_limits
 * (coil_choice.saturation_current_limit).  The Python is the reference: the same names (ct_scp_
 * prefix), the same scalar operations in the same order; the products the reference hands to BLAS
 * (F P F^T, Hu P6, A Hu^T, Si A, A^T G) are summed in increasing index order, so they agree to
 * rounding, not bit for bit.  Every buffer is caller-owned, row-major.
 */
#ifndef CT_SC_POLICY_H
#define CT_SC_POLICY_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

struct ct_sc;

/* st[]: a reference's scalars after a propagation */
enum { CT_REF_ELAPSED = 0, CT_REF_MEAN = 1, CT_REF_SETTLED = 2, CT_REF_A = 3, CT_REF_NST = 4 };

/* one FixedCycleReference's buffers (the core block, 15 x 15) and constants */
struct ct_scref {
    double *P, *F, *q, *T;             /* 15 x 15, 15 x 15, 15, 15 x 15 scratch */
    double *avg, *law;                 /* 6, 2 */
    double *own;                       /* 2 (MeanBudgetReference), or NULL */
    double *st;                        /* CT_REF_NST */
    double warmup_us, avg_us, exp[2];
};

void ct_scp_ref_propagate(const struct ct_sc *s, struct ct_scref *r, double dt, int64_t dt_us, double elapsed_us,
                          double mean_us, int settled, double settle_drop);

/* PoseCovUpdate's scratch */
struct ct_scp_cov {
    double A[18], M[9], G[18], Si[9], T[36], T2[36];
};
int ct_scp_pose_cov_update(struct ct_scp_cov *w, double *P6, const double *Hu, const double *hu, double current,
                           double var_amp, double rel_model, double current_sigma);

void ct_scp_ref_pulse_fill(int nx, double *H, double *R, double *y, const double *Hu, const double *hu,
                           double current, double var_amp, double rel_model, double current_sigma, int pos, int ori);

/* one coil_choice.NisMonitor: its ring (window), the chi-square bounds by count (window + 1), the
 * state (CT_NIS_NST: the integers and the flag held as doubles) and its constants */
enum { CT_NIS_COUNT, CT_NIS_HEAD, CT_NIS_MEAN, CT_NIS_INCONSISTENT, CT_NIS_R_SCALE, CT_NIS_TOTAL, CT_NIS_FLAGGED,
       CT_NIS_EXCESS, CT_NIS_NST };
struct ct_nis {
    double *buf, *st;
    const double *bound;
    int window, min_count;
    double dof, min_mean, max_scale, excess_gate, alpha;
};
void ct_nis_add(struct ct_nis *m, double x);
void ct_nis_add_used(struct ct_nis *m, double x);

double ct_scp_saturation_current_limit(const double *hu, const double *quiet, double range_t, double margin,
                                       double gain);
void ct_scp_range_limits(int n, const double *h, const double *pp, const double *P6, const double *quiet,
                         int have_quiet, double saturation_sigmas, double range_t, double margin,
                         double earth_max_t, double *lim);

/* one sensor's decision bounds (AdaptiveActuation._bounds): the view's arrays, its reference's
 * (NULL: no reference) and the mean budget's (NULL: the plain reference), the configuration */
enum { CT_BND_RATIO, CT_BND_MIN_RATIO, CT_BND_CATCHUP, CT_BND_NIS, CT_BND_NIS_MAX, CT_BND_HOLD_MIN,
       CT_BND_HOLD_MAX, CT_BND_SMAX_POS, CT_BND_SMIN_POS, CT_BND_SMAX_ORI, CT_BND_SMIN_ORI, CT_BND_RANGE_REF,
       CT_BND_EXP_POS, CT_BND_EXP_ORI, CT_BND_REF_EXP0, CT_BND_REF_EXP1, CT_BND_N };
struct ct_scp_bounds {
    const double *pp;                  /* 3: the predicted position */
    double *mx, *mn;                   /* 6, 6: the bounds (m, rad) */
    const double *avg, *law, *P;       /* 6, 2, 15 x 15: the reference's */
    const double *own;                 /* 2: the mean budget's (NULL: none) */
    double *factor, *held;             /* 2, 6: the mean budget's held means */
    double c[CT_BND_N];
};
void ct_scp_bounds(struct ct_scp_bounds *b, int ref_active, int warming, double excess);

/* ------------------------------------------------------------ the pulses' book and command
 * PulseSchedule.command's COIL_PULSE_CMD frame (payload "<BHhQI": coil, pulse_id, current_ma,
 * start_us, duration_us) as ct_flip_frame makes a MAG_FLIP_CMD (-1: a value struct.pack refuses) */
enum { CT_PCMD_ID = 0x10, CT_PCMD_PAYLOAD = 17, CT_PCMD_CRC_EXTRA = 0xDE,
       CT_PCMD_FRAME_RAW = 5 + 17 + 2, CT_PCMD_FRAME_MAX = 5 + 17 + 2 + 2 + 1 };
int ct_pulse_cmd_frame(uint8_t *out, int seq, int src, int64_t coil, int64_t pulse_id, int64_t current_ma,
                       uint64_t start_us, int64_t duration_us);
/* single_coil_pulses.PulseBook.duty_ok over coil c's (start, end) pairs (hist: n_hist of them,
 * flat); bound = duty_margin * coil_max_duty * coil_duty_window_us as the reference computes it */
int ct_scp_duty_ok(const int64_t *hist, int n_hist, int64_t start, int64_t length, int64_t window_us, double bound);

/* coil_choice.ActuationPolicy (when a pulse is due, Schepers sec. 2.1): var_max (6) set from the
 * bounds (set_bounds), the worst normalised std (worst) and the due test (due; *reason 0 none,
 * 1 uncertainty, 2 interval); trace: the position and orientation blocks' traces bounded */
void ct_scp_policy_set_bounds(double *var_max, const double *sigma_max6);
double ct_scp_policy_worst(const double *var_max, const double *P6, int trace);
int ct_scp_policy_due(const double *var_max, const double *P6, int trace, int64_t now_us, int64_t last_update_us,
                      int64_t max_interval_us, int *reason);

#ifdef __cplusplus
}
#endif

#endif /* CT_SC_POLICY_H */
