/*
 * The per-IMU-sample path of the fused trackers (core/src/fusimu.c): the fusion filter's
 * input interpolation and step (coiltrack.firmware.estimate.fusion_prediction.InertialPrediction
 * .propagate, .set_dt), its pose history and fused output rows (fusion_state.MovingSource /
 * FixedSource .to_source, .position_var, fusion_output.PoseOutput.queue, _quat_into,
 * rotation.quat_from_elements), and the orientation filter's per-sample prediction
 * (estimate.orientation.OrientationFilter.predict) with the choice of its compass sample
 * (track.burst_fusion.quiet_sample).  The same operations in the same order as
 * the Python reference; state in caller-owned buffers.
 */
#ifndef CT_FUSIMU_H
#define CT_FUSIMU_H

#include <stdint.h>

/* the IMU ring's row (fusion_state.IMU_FIELDS): F, W, FSRC, PHI */
enum { CT_IMU_F = 0, CT_IMU_W = 3, CT_IMU_FSRC = 6, CT_IMU_PHI = 9, CT_IMU_WIDTH = 18 };
/* a pose-history row (fusion_state.HIST_FIELDS): P, R */
enum { CT_HIST_P = 0, CT_HIST_R = 3, CT_HIST_WIDTH = 12 };
/* an output row (fusion_output.OUT_FIELDS) and its status bits */
enum { CT_OUT_P = 0, CT_OUT_Q = 3, CT_OUT_VAR_P = 7, CT_OUT_VAR_O = 10, CT_OUT_STATUS = 13, CT_OUT_WIDTH = 14 };
enum { CT_OUT_STALE = 1, CT_OUT_INCONSISTENT = 2, CT_OUT_DEAD_RECKONING = 4, CT_OUT_LOST = 8,
       CT_OUT_RECOVERED = 16 };
/* the step's workspace scalars (InsState.dt_last, ka, kg) */
enum { CT_FS_DT_LAST = 0, CT_FS_KA = 1, CT_FS_KG = 2, CT_FS_NST = 3 };

/* one inertial state's prediction (InertialPrediction bound to one InsState) */
struct ct_fus_pred {
    struct ct_ins ins;              /* the state's buffers (ct_ins_propagate) */
    double *Q;                      /* n x n, the diagonals set_dt writes */
    const int64_t *itv;             /* the IMU ring's times (icap) */
    const double *idv;              /* its rows (icap x CT_IMU_WIDTH) */
    int icap;
    double dtk[6];                  /* InertialPrediction._dtk: tau_a, tau_g, qv_k, gyro_noise, qa_k, qg_k */
    double *st;                     /* CT_FS_NST */
};
/* the step's static blocks of ins->A and Q's diagonal, ws[CT_FS_NST] (InertialPrediction.set_dt) */
void ct_fus_set_dt(const struct ct_ins *ins, double *Q, const double *dtk, double *ws, double dt);
/* one step of the state ins (its Q, dtk, ws) over [t0, t1] with slots k - 1 and k of the IMU ring
 * (times itv, rows idv, icap slots, nring held): the forward path's and the replay's */
void ct_fus_step(const struct ct_ins *ins, double *Q, const double *dtk, double *ws, const int64_t *itv,
                 const double *idv, int64_t icap, int64_t k, int64_t nring, int64_t t0, int64_t t1);
void ct_fus_propagate(const struct ct_fus_pred *f, int k, int nring, int64_t t0, int64_t t1);
/* history row hd (CT_HIST_WIDTH) of p, Th in the source frame (Phi of IMU row d; moving: 0 = fixed) */
void ct_fus_to_source(const double *d, int moving, const double *p, const double *Th, double *hd);
void ct_quat_from_elements(const double *r, double *q);
/* one output row od (CT_OUT_WIDTH) from history row hd, the state's P (n x n) and Th, IMU row d */
void ct_fus_output(double *od, const double *hd, const double *P, int n, const double *Th, const double *d,
                   int moving, double status);
int ct_fus_status(int64_t age, int64_t stale_us, int64_t dr_after_us, int64_t dr_limit_us, int recovering,
                  int inconsistent);

/* the orientation filter's per-sample prediction; its accumulators in acc[CT_OA_N]
 * (OrientationFilter._dt_acc, _dt2_acc, _cd_acc, _qd_acc, _ca and Inclination._dt) */
enum { CT_OA_DT = 0, CT_OA_DT2 = 1, CT_OA_CD = 2, CT_OA_QD = 3, CT_OA_CA = 4, CT_OA_INCL_DT = 5, CT_OA_N = 6 };
struct ct_ori_pred {
    double *R, *bias, *dist, *acc, *E;  /* 9, 3, 3, 3, 9 (scratch) */
    double *st;                         /* CT_OA_N */
    double dist_corr, acc_corr_time_s;
};
void ct_ori_predict(const struct ct_ori_pred *o, double dt, double wx, double wy, double wz, double qwd);

/* the orientation filter's two updates around the one Kalman update (ct_kalman_update, run by the
 * caller between them): orientation_updates.Inclination.update's and Compass.update's measurement
 * (y, H, R), OrientationFilter._apply and _post_acc.  The compass state cst[CT_CS_N]
 * (orientation_updates.Compass.state); the last accelerometer sample and its difference from the
 * predicted acceleration in sc[CT_OS_N]. */
enum { CT_CS_MREF = 0, CT_CS_QWD = 1, CT_CS_NORM = 2, CT_CS_DIP = 3, CT_CS_N = 4 };
enum { CT_OS_AX = 0, CT_OS_AY, CT_OS_AZ, CT_OS_VX, CT_OS_VY, CT_OS_VZ, CT_OS_VN, CT_OS_N };
struct ct_ori_meas {
    int n, theta, bias, dist;           /* the layout's rows (layout.ORIENTATION_LAYOUT) */
    double *R, *Rc, *b, *d, *a, *E;     /* 9, 9, 3, 3, 3, 9 (scratch) */
    const double *sums;                 /* CT_OA_N (ct_ori_pred's) */
    double *iy, *iH, *iR;               /* the inclination update's y (3), H (3 x n), R (3 x 3) */
    const double *idx;                  /* its correction (n) */
    double *my, *mH, *mR;               /* the compass update's */
    const double *mdx;
    const double *hg;                   /* 3: the earth field's direction, global frame */
    double *cst;                        /* CT_CS_N */
    double sc[CT_OS_N];
    double gravity, freefall_tolerance, acc_noise, acc_motion_sigma, acc_adapt_gain;
    double mag_noise, dist_sigma, dist_norm_gain, dist_dip_gain, dist_smoothing;
    int heading_only;
};
int ct_ori_incl_begin(struct ct_ori_meas *o, double ax, double ay, double az, double motion_ms);
void ct_ori_apply(const struct ct_ori_meas *o, const double *dx);
void ct_ori_post_acc(const struct ct_ori_meas *o);
void ct_ori_compass_fill(const struct ct_ori_meas *o, double mx, double my, double mz);

/* the compass sample of an orientation filter (track.burst_fusion.quiet_sample with
 * measure.pulse.SampleRing.nearest_slot and PulseGate.quiet): the magnetometer ring's times tv and
 * flags fl (cap slots; bit CT_SAMPLE_SATURATED, ct_window.h), the pulse schedule's starts ps and ends pe (n pulses), the gate's margins */
struct ct_quiet {
    const int64_t *tv;
    const uint8_t *fl;
    int64_t cap;
    const int64_t *ps, *pe;
    int64_t n, before, after;
};
/* the slot of the sample nearest t_imu in the ring at (head, count) if newer than after_t, within
 * max_age_us of t_imu, not saturated and outside the pulses; else -1 */
int64_t ct_quiet_sample(const struct ct_quiet *q, int64_t head, int64_t count, int64_t after_t, int64_t t_imu,
                        int64_t max_age_us);

/* one IMU sample of an orientation filter fed from a magnetometer ring (track.burst_fusion._Ori.step
 * on an initialised filter whose compass has learned |m|, with OrientationFilter.predict,
 * update_acc, update_mag, propagate, Inclination.observe, FlipOffset.observe and the two
 * KalmanUpdate.update with their periodic symmetrisation): the compass sample (ct_quiet_sample),
 * the set/reset offset, the prediction and, every `every` samples, the two updates. */
/* FlipOffset's state: fl[CT_FL_*] (the offset o and the previous sample), fi[CT_FI_*] */
enum { CT_FL_O = 0, CT_FL_PREV = 3, CT_FL_N = 6 };
enum { CT_FI_STATE = 0, CT_FI_T = 1, CT_FI_N = 2, CT_FI_COUNT = 3 };
/* Inclination's motion level: inc[CT_IN_*] (motion_ms, the running mean, the mean square, started) */
enum { CT_IN_MOTION = 0, CT_IN_MEAN = 1, CT_IN_SQ = 4, CT_IN_STARTED = 5, CT_IN_N = 6 };
/* the result's bits: a prediction step ran; an update round ran; the inclination's Kalman update
 * ran (its ekf flags at CT_OS_ACC_SHIFT) or it was free fall; the compass's ran (flags at
 * CT_OS_MAG_SHIFT); the covariance propagations (count at CT_OS_PROP_SHIFT) */
enum { CT_OS_PREDICTED = 1, CT_OS_ROUND = 2, CT_OS_ACC = 4, CT_OS_FREEFALL = 8, CT_OS_MAG = 16,
       CT_OS_ACC_SHIFT = 8, CT_OS_MAG_SHIFT = 12, CT_OS_PROP_SHIFT = 16 };
struct ct_ori_step {
    struct ct_ori_pred pred;
    struct ct_ori_meas meas;
    struct ct_ori prop;                 /* its T is also the symmetrisation's scratch */
    struct ct_kalman iu, mu;            /* the inclination's and the compass's update */
    double igate, mgate;
    double *inis, *mnis;                /* 1 each: the updates' NIS */
    struct ct_quiet q;
    const double *mb;                   /* the magnetometer ring's fields (cap x 3) */
    double *fl;                         /* CT_FL_N */
    int64_t *fi;                        /* CT_FI_COUNT */
    double flip_gain;
    double *inc;                        /* CT_IN_N */
    double acc_adapt_tau_s;
    int64_t *ct;                        /* 1: the last compass sample's time */
    int every;                          /* _Ori.every: an update round every `every` samples */
    int symmetrize_every;               /* ekf.SYMMETRIZE_EVERY */
    int64_t max_age_us;
};
/* the sample (t, f, w) at step `steps`, update-round counter n, after the prediction at t_prev;
 * the magnetometer ring at (head, count); the counts of the propagations (pcount) and of the two
 * updates (icount, mcount) decide the symmetrisations.  Returns the CT_OS_* bits. */
/* the two halves of ct_ori_sample, for a sample whose prediction the caller follows with its
 * orthonormalisation: up to the prediction (the compass sample into m[CT_OM_*]), and the update round */
enum { CT_OM_FOUND = 0, CT_OM_X = 1, CT_OM_Y = 2, CT_OM_Z = 3, CT_OM_N = 4 };
int ct_ori_sample_begin(const struct ct_ori_step *o, int64_t t, double wx, double wy, double wz, int64_t t_prev,
                        int64_t head, int64_t count, double *m);
int ct_ori_sample_end(const struct ct_ori_step *o, double ax, double ay, double az, int n, const double *m,
                      int64_t pcount, int64_t icount, int64_t mcount);
int ct_ori_sample(const struct ct_ori_step *o, int64_t t, double ax, double ay, double az, double wx, double wy,
                  double wz, int64_t t_prev, int n, int64_t head, int64_t count, int64_t pcount, int64_t icount,
                  int64_t mcount);
/* orientation.OrientationFilter._orthonormalize (R row-major 3x3, in place), and ct_ori_sample with it after
 * the prediction when that is the filter's step number a multiple of 64 (steps: the filter's steps before the
 * sample; OrientationFilter.predict's `steps & 63 == 0`) */
enum { CT_ORI_ORTHO_MASK = 63 };
void ct_ori_orthonormalize(double *R);
int ct_ori_sample_ortho(const struct ct_ori_step *o, int64_t t, double ax, double ay, double az, double wx,
                        double wy, double wz, int64_t t_prev, int n, int64_t head, int64_t count, int64_t pcount,
                        int64_t icount, int64_t mcount, int64_t steps);
void ct_flip_observe(double *fl, int64_t *fi, double gain, int64_t t_us, int state, double mx, double my,
                     double mz, double rx, double ry, double rz, int64_t max_dt_us);
void ct_incl_observe(double *inc, const double *R, double gravity, double gain, double tau, double ax, double ay,
                     double az, double dt);
void ct_symmetrize(int n, double *P, double *T);

/* ring.Ring.push / pop on a ring whose head and count are hc[0], hc[1] (fusion_rings.KernelRing):
 * the slot pushed (its time written into tv) or popped (-1: empty) */
int64_t ct_ring_push(int64_t *hc, int64_t cap, int64_t *tv, int64_t t);
int64_t ct_ring_pop(int64_t *hc, int64_t cap);
/* measure.imu.ImuRing.push: the sample at t (s: ax, ay, az in ACC_LSB, gx, gy, gz in GYR_LSB) into the
 * ring (times tv, rows d of 6: specific force, rate), its state st[CT_IR_N]: the last time taken,
 * the samples dropped (not newer, or overwriting a full ring's oldest) and received */
enum { CT_IR_LAST_T = 0, CT_IR_DROPPED = 1, CT_IR_RECEIVED = 2, CT_IR_N = 3 };
void ct_imu_ring_push(int64_t *hc, int64_t cap, int64_t *tv, double *d, int64_t *st, int64_t t, const double *s,
                      double acc_lsb, double gyr_lsb);

/* The per-sample state of a fused tracker's sensor as its owners keep it in int64 arrays, read and
 * written by the one-call IMU sample in place (track.burst_fusion._OneCall.run):
 * OrientationFilter.state (CT_OF_*), FusionFilter.fs (CT_FF_*) and the counts beside them. */
enum { CT_OF_INIT = 0, CT_OF_T = 1, CT_OF_STEPS = 2, CT_OF_ACCF = 3, CT_OF_MAGF = 4, CT_OF_N = 5 };
enum { CT_FF_INIT = 0, CT_FF_UPDATE_T = 1, CT_FF_FLAGS = 2, CT_FF_RECORDER = 3, CT_FF_REPLAYING = 4, CT_FF_N = 5 };
/* fusion_snapshot.Snapshot.sq: its time, pending, valid, initialized, xi */
enum { CT_SQ_T = 0, CT_SQ_PENDING = 1, CT_SQ_VALID = 2, CT_SQ_INIT = 3, CT_SQ_XI = 4, CT_SQ_N = 5 };
/* orientation.ORI_FREEFALL; magnetic_inertial.FUS_INITIALISED | FUS_GAP_REINIT */
enum { CT_ORI_FREEFALL = 128, CT_FUS_FRESH_FLAGS = 512 | 16384 };
struct ct_sample_state {
    int64_t *of;                        /* OrientationFilter.state, CT_OF_N */
    const int64_t *learn;               /* 1: Compass.learn_state (learning, 0/1) */
    int64_t *ns;                        /* 2: _Ori.ns (n, compass_used) */
    int64_t *opc;                       /* 1: the orientation filter's CovariancePredict count */
    int64_t *ik, *mk;                   /* 2 each: the inclination's and the compass's KalmanUpdate (count, rejected) */
    const int64_t *ff;                  /* FusionFilter.fs, CT_FF_N */
    int64_t *ts;                        /* 1: the live InsState's time */
    int64_t *fpc;                       /* 1: its CovariancePredict count */
    int64_t *ps;                        /* 1: InertialPrediction's steps */
    int64_t *sq;                        /* CT_SQ_N: the Snapshot's time and flags */
    const int64_t *rs;                  /* 1: Recovery's recovering (0/1) */
    const int64_t *mhc;                 /* 2: the magnetometer ring's head and count */
    int64_t gap_us;                     /* _Ori.gap_us */
    int64_t max_gap_us;                 /* FusionParams.max_gap_us */
};
/* where the sample at t goes (_OneCall.run's tests): CT_SR_WHOLE through ct_ori_sample and the fusion
 * filter's live step in one call; CT_SR_SLOW not (_Ori.settled, FusionFilter.live_ready: the steps
 * one by one); CT_SR_ORTHO both filters take it but its prediction may orthonormalise the
 * orientation (OrientationFilter.sample_done's): ct_ori_sample_ortho in the same one call */
/* CT_SR_SNAP: both filters take it but a pending snapshot falls inside its step (FusionFilter._advance's
 * split step, the snapshot taken in it when no replay runs): the caller tests that it can take it so */
enum { CT_SR_WHOLE = 0, CT_SR_SLOW = 1, CT_SR_ORTHO = 2, CT_SR_SNAP = 3 };
int ct_sample_route(const struct ct_sample_state *s, int64_t t);
/* the bookkeeping of a sample at t the one call ran (its CT_OS_* bits r): InertialPrediction.sampled,
 * then _Ori.sampled with OrientationFilter.sample_done (KalmanUpdate.counted for the updates run) */
void ct_sample_done(const struct ct_sample_state *s, int64_t t, int r);
/* ct_sample_done's second half alone (_Ori.sampled with OrientationFilter.sample_done) */
void ct_sample_done_ori(const struct ct_sample_state *s, int64_t t, int r);
/* OrientationFilter.propagate on the compiled core (the covariance over the steps since the last call,
 * CovariancePredict.after_predict's symmetrisation after its count-th prediction, _restart_sums): 1 when it ran */
int ct_ori_propagate_now(const struct ct_ori_step *o, int64_t count);

#endif /* CT_FUSIMU_H */
