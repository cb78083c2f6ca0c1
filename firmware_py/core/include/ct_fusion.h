/*
 * The fusion filter's delayed magnetic update and its replay (compiled core).
 *
 * References (the Python is the specification, followed operation by operation):
 *   coiltrack.firmware.estimate.fusion_measurement (MagneticOrientation.evaluate,
 *     InertialMagneticOrientation.evaluate, _position_and_white, _log_diff) and
 *     coiltrack.firmware.linalg.rotvec_from_matrix;
 *   coiltrack.firmware.estimate.fusion_state.InsState.correct and copy_from;
 *   coiltrack.firmware.estimate.magnetic_inertial.FusionFilter.step and _advance, with
 *     fusion_prediction.InertialPrediction.propagate, set_dt, step_compiled and history,
 *     fusion_state.MovingSource / FixedSource.to_source, ring.Ring.push / index_at_or_after and
 *     ekf.CovariancePredict.after_predict.
 * Thesis seeds/002_cd7f1fdb7fc67471.txt: measurement models eqs 6.18, 6.20, 6.21 (sec 6.2.5),
 * the white blocks' covariance (sec 6.5), strapdown eqs 6.1-6.4, 6.8, transition eq 6.17 and
 * the delayed update's rewind and replay (sec 6.2.3).
 */
#ifndef CT_FUSION_H
#define CT_FUSION_H

#include <stdint.h>

/* ------------------------------------------------------------ measurement
 * One model's constants (fusion_measurement._Base and its prm), fixed at start-up.  Row indices:
 * zp, zpsi, zxi of y (-1: the model has no such rows); q0, s0, x0 of the state (QM, PSI, XI;
 * x0 -1 for model 1); cp, co of the solver's covariance C (POSE_POS, POSE_ORI). */
/* pose.covariance.MARGIN_MAX_ORI_VAR (rad^2), checked against it at start-up (fusion_measurement.py) */
#define CT_MARGIN_MAX_ORI_VAR 1.0
struct ct_fusmeas {
    int n;
    int zp, zpsi, zxi;
    int q0, s0, x0;
    int cp, co;
    double mag_var_scale;       /* prm.mag_var_scale */
    double xi_var_scale;        /* prm.xi_var_scale */
    double xi_floor2;           /* prm.xi_sigma_floor ** 2 */
    double xi_heading_floor2;   /* prm.xi_heading_sigma_floor ** 2 */
    double psi_var;             /* prm.psi_sigma ** 2 */
};
/* linalg.rotvec_from_matrix of r (row-major 3x3) into w (3) */
void ct_fusion_rotvec_from_matrix(const double *r, double *w);
/* MagneticOrientation.evaluate (xi_model 0) / InertialMagneticOrientation.evaluate (1): the
 * innovation into y and the white blocks of P (n x n); Psi (9) is the model's scratch
 * (Psi = Phi R_ms); Xi, XiP (9 each) the snapshot's, read by models 2 and 3 only. */
void ct_fusion_evaluate(const struct ct_fusmeas *m, int xi_model, const double *Phi, const double *Xi,
                        const double *XiP, const double *q, const double *R_ms, const double *C,
                        const double *p, const double *Th, double *P, double *y, double *Psi);

/* ------------------------------------------------------------ the state
 * One InsState's nominal state and covariance (fusion_state.InsState). */
struct ct_fusstate {
    int n;
    double *p, *v, *Th, *ba, *bg, *P;     /* 3, 3, 9, 3, 3, n x n */
};
/* InsState.correct: p, v, b_a, b_g += dx; Theta <- exp([dx_ori]x) Theta */
void ct_fusion_correct(const struct ct_fusstate *s, const double *dx);
/* InsState.copy_from (the nominal state and covariance; the time is the caller's) */
void ct_fusion_copy(const struct ct_fusstate *dst, const struct ct_fusstate *src);

/* ------------------------------------------------------------ the replay
 * FusionFilter.step on the compiled core, bound to the shadow state (its InsStep buffers), the
 * IMU ring and the shadow pose history.  The Python attributes it reads and advances live in the
 * caller's io (int64) and fo (double) arrays, indexed by these: */
enum {
    CT_RIO_T = 0,           /* in/out: the shadow's t_us */
    CT_RIO_IMU_FIRST,       /* in: the IMU ring's oldest slot (Ring.slot(0)) */
    CT_RIO_IMU_COUNT,       /* in: len(imu) */
    CT_RIO_HIST_FIRST,      /* in: the shadow history's oldest slot */
    CT_RIO_HIST_COUNT,      /* in: len(history.shadow) */
    CT_RIO_HIST_PUSHED,     /* out: entries pushed onto the shadow history by this call */
    CT_RIO_SNAP_PENDING,    /* in: snap.pending */
    CT_RIO_SNAP_T,          /* in: snap.t */
    CT_RIO_UNITS,           /* in/out: strapdown steps of this FusionFilter.step call so far */
    CT_RIO_PRED_COUNT,      /* in/out: the shadow's CovariancePredict.count */
    CT_RIO_STEPS,           /* out: strapdown steps run by this call */
    CT_RIO_SPLIT,           /* in/out: -1, or the IMU slot whose step was split at the snapshot time:
                               the snapshot is to be taken, then the call resumes with its rest */
    CT_RIO_N
};
/* InsState.dt_last, ka, kg: the step's scalars ct_fus_step keeps (ct_fusimu.h's CT_FS_*) */
enum { CT_RFO_DT_LAST = CT_FS_DT_LAST, CT_RFO_KA = CT_FS_KA, CT_RFO_KG = CT_FS_KG, CT_RFO_N = CT_FS_NST };
/* what ct_fusion_replay stopped at */
enum { CT_REPLAY_CAUGHT_UP = 0, CT_REPLAY_BUDGET = 1, CT_REPLAY_LOST = 2, CT_REPLAY_SNAPSHOT = 3 };
/* the IMU ring's row (CT_IMU_*) and the pose-history row (CT_HIST_*): ct_fusimu.h */
struct ct_replay {
    struct ct_ins ins;              /* the shadow's strapdown and covariance step (strapdown.c) */
    double *Qd;                     /* = ins.Q, written by set_dt's diagonal */
    int fixed;                      /* FixedSource: no frame change */
    int imu_cap, hist_cap;
    const int64_t *imu_t;           /* imu_cap */
    const double *imu_d;            /* imu_cap x CT_IMU_WIDTH */
    int64_t *hist_t;                /* hist_cap */
    double *hist_d;                 /* hist_cap x CT_HIST_WIDTH */
    double dtk[6];                  /* InertialPrediction._dtk */
    int symmetrize_every;           /* ekf.SYMMETRIZE_EVERY */
};
/* Replay IMU samples on the shadow until it has caught up with the newest one, the budget of
 * strapdown steps is spent, the sample before the next one left the ring, or a pending snapshot
 * falls in the next sample (then the step is split: the part up to the snapshot time is run,
 * io[CT_RIO_SPLIT] names the slot, and the caller takes the snapshot and calls again). */
int ct_fusion_replay(const struct ct_replay *r, int64_t *io, double *fo, int budget);

/* ------------------------------------------------------------ the burst's side
 * fusion_snapshot.Snapshot.take_aux (with orientation.OrientationFilter.theta_covariance_global,
 * its propagate run by the caller first): Phi of IMU row imu_row (fixed: the identity) into Phi;
 * when xi (the ch. 2 filter is initialised): Xi = R, XiP = R P[t0:t0+3, t0:t0+3] R^T (P: np x np),
 * XiB = bias.  All 3x3 row-major. */
void ct_fusion_snap_aux(int fixed, const double *imu_row, int xi, const double *R, const double *P, int np, int t0,
                        const double *bias, double *Phi, double *Xi, double *XiP, double *XiB);
/* fusion_output.PoseHistory.pose_at over the live history (times ht, rows hd of CT_HIST_WIDTH,
 * capacity cap, head and count as ring.Ring keeps them): the pose at t_us interpolated into
 * out_p (3) and out_R (9, row-major); 0 when t_us is outside the history. */
int ct_fusion_pose_at(const int64_t *ht, const double *hd, int64_t cap, int64_t head, int64_t count, int64_t t_us,
                      double *out_p, double *out_R);
/* track.burst_fusion.SensorInertial.motion_cov: out (6x6) = C plus the motion left in a burst
 * solved at p, with the live state's covariance P (n x n) and velocity v, the rate w (w_last),
 * tr2 = burst_rms_s^2; compensated: the velocity's uncertainty (InsState.velocity_sigma), else
 * the rate and (initialized) the speed (InsState.speed_squared). */
void ct_fusion_motion_cov(const double *C, double *out, const double *p, int compensated, int initialized,
                          double tr2, const double *P, int n, const double *v, const double *w);

/* SensorInertial.compensate_begin's checks and copies: S_comp (3 x n) = S; then false (0) when the
 * filter is not initialised or its velocity's rms uncertainty (InsState.velocity_sigma of the live
 * covariance P, n_st x n_st) exceeds max_sigma, else ct_fusion_pose_at at t_ref into p_ref, R_ref */
int ct_fusion_comp_begin(const double *S, double *S_comp, int n, int initialized, const double *P, int n_st,
                         double max_sigma, const int64_t *ht, const double *hd, int64_t cap, int64_t head,
                         int64_t count, int64_t t_ref, double *p_ref, double *R_ref);
/* compensate_step's correction of pulse j: S_comp[:, j] = S_comp[:, j] + h_ref[:, j] - h_j[:, j] */
void ct_fusion_comp_add(double *S_comp, const double *h_ref, const double *h_j, int n, int j);

/* fusion_output.PoseHistory.rewind_shadow / commit: ring.Ring.copy_from of one pose history (times t, rows d of
 * CT_HIST_WIDTH, capacity cap, (head, count) hc) into the other, then (drop: rewind) Ring.drop_newer_than(t_us) */
void ct_fusion_hist_copy(int64_t *dt, double *dd, int64_t *dhc, const int64_t *st, const double *sd, const int64_t *shc,
                         int64_t cap, int drop, int64_t t_us);

/* ------------------------------------------------------------ the update in one call each
 * FusionFilter.prepare_magnetic_update's restore (_restore): the shadow = the snapshot's state
 * (ct_fusion_copy), its pose history = the live one up to t_ref (ct_fusion_hist_copy with the
 * drop: live_* the source, shadow_* the destination), the measurement model's evaluate
 * (ct_fusion_evaluate, m bound to the shadow's p, Th, P and the snapshot's Phi, Xi, XiP). */
struct ct_fusprep {
    const struct ct_fusmeas *m;
    int xi_model;
    const double *Phi, *Xi, *XiP;
    double *y, *Psi;
    const struct ct_fusstate *shadow, *snap;
    int64_t *live_t, *live_hc, *shadow_t, *shadow_hc;
    double *live_d, *shadow_d;
    int64_t hist_cap;
    int64_t *hist_mark;             /* PoseHistory.mark: the rewind copies in part (ct_hist_sync); NULL: whole */
};
void ct_fusion_prepare(const struct ct_fusprep *f, int64_t t_ref, const double *q, const double *R_ms,
                       const double *C);
/* FusionFilter._update_shadow: the Kalman update of the shadow's P (ct_kalman_update, the one
 * shape), accepted: InsState.correct with its dx and, when sym, ekf.symmetrize (what
 * KalmanUpdate.update does every SYMMETRIZE_EVERY accepted updates).  Returns the flags. */
int ct_fusion_update(const struct ct_kalman *u, const struct ct_fusstate *s, double gate, int sym, double *nis);

#endif /* CT_FUSION_H */
