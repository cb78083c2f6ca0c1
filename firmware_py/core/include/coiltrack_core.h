/*
 * coiltrack compiled core: the firmware's numeric kernels in C99.
 *
 * Written as firmware: no allocation, no global mutable state, only <math.h>,
 * <string.h> and <stdint.h>; every state and scratch lives in caller-owned
 * buffers.  The Python modules named beside each function are the reference
 * and the specification: the C follows them function by function, with the
 * same names (prefixed ct_) and the same floating-point operations in the
 * same order, so that with -ffp-contract=off the results are bit-identical.
 *
 * Matrices are row-major, C-contiguous doubles, as numpy lays them out.
 */
#ifndef COILTRACK_CORE_H
#define COILTRACK_CORE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ------------------------------------------------------------------ field
 * coiltrack.firmware.model.field: loop_point, dipole_point.
 * out[0..2] = (bx, by, bz); with jac, out[3..8] = (jxx, jyy, jzz, jxy, jxz, jyz).
 */
void ct_loop_point(double x, double y, double z, double radius, double scale, int jac, double *out);
void ct_dipole_point(double px, double py, double pz, double mx, double my, double mz, int jac,
                     double *out);

/* ----------------------------------------------------------------- signal
 * coiltrack.firmware.model.signal.SignalModel.  The coil geometry is packed
 * once (start-up) into CT_COIL_STRIDE doubles per coil, in this order:
 */
enum {
    CT_COIL_KIND = 0,     /* CT_KIND_LOOP, CT_KIND_LOOP_AXES or CT_KIND_DIPOLE */
    CT_COIL_CENTER = 1,   /* 3: centre, m (source frame) */
    CT_COIL_ROT = 4,      /* 9: rotation coil -> source frame, row-major */
    CT_COIL_AXIS = 13,    /* 3: unit axis */
    CT_COIL_RADIUS = 16,  /* loop radius, m */
    CT_COIL_SPA = 17,     /* mu0 N gain / (2 pi a), T per A */
    CT_COIL_MPA = 18,     /* N gain pi a^2, A m^2 per A */
    CT_COIL_PERM = 19,    /* 6: (i0, s0, i1, s1, i2, s2) of a signed-permutation rotation */
    CT_COIL_STRIDE = 25
};
enum { CT_KIND_LOOP = 0, CT_KIND_LOOP_AXES = 1, CT_KIND_DIPOLE = 2 };

/* B (n, 3) and, with jac, J (n, 3, 3): every coil's source-frame field and gradient at p
 * for the currents cur (n), A.  SignalModel.fields without the distortion map. */
void ct_signal_fields(const double *geom, int n, double px, double py, double pz, const double *cur,
                      int jac, double *B, double *J);
/* h (3n) = R^T B_j (SignalModel.predict's projection; R sensor -> source, row-major 3x3). */
void ct_signal_project(int n, const double *R, const double *B, double *h);
/* h (3n) and H (3n x 6) from B, J (SignalModel.measure's projection, Schepers eqs 9-11). */
void ct_signal_project_jac(int n, const double *R, const double *B, const double *J, double *h,
                           double *H);

/* ------------------------------------------------------------------- ekf
 * coiltrack.firmware.estimate.ekf.CovariancePredict.predict: P <- A P A^T + Q (n x n, row-major),
 * A's zero entries skipped; T is n x n scratch. */
/* P <- A P A^T alone (A's zero entries skipped): the prediction without its noise */
void ct_congruence_sparse(int n, const double *A, double *P, double *T);
void ct_covariance_predict(int n, const double *A, double *P, const double *Q, double *T);

/* KalmanUpdate.update (estimate.ekf): the one update shape of every filter.  The caller owns
 * every buffer (row-major): H (m x n), R (m x m), y (m), dx (n), S, Sinv (m x m), K (n x m), and
 * the scratch PHt, TH, KR (n x m), T, X (n x n), w (m), L, M (m x m). */
enum { CT_EKF_OK = 0, CT_EKF_GATED = 1, CT_EKF_NOT_PD = 2, CT_EKF_NONFINITE = 4 };
struct ct_kalman {
    int n, m;
    const double *H, *R, *y;
    double *dx, *S, *Sinv, *K, *PHt, *T, *TH, *X, *KR, *w, *L, *M;
};
int ct_inv3(const double *s, double *out);
int ct_spd_inverse(int n, const double *a, double *out, double *L, double *M);
int ct_kalman_update(const struct ct_kalman *u, double *P, double gate, double *nis_out);
/* binds the update's 15 buffers in KalmanUpdate's order: H R y dx S Sinv K PHt T TH X KR w L M */
void ct_kalman_bind(struct ct_kalman *u, int n, int m, double *const *buf);

/* ------------------------------------------------------------- strapdown
 * coiltrack.firmware.estimate.strapdown, linalg.exp_rotvec and FusionFilter._propagate.
 * The inertial rows of every inertial layout (estimate.layout: POS, VEL, ORI, ACC, GYR). */
enum { CT_POS = 0, CT_VEL = 3, CT_ORI = 6, CT_ACC = 9, CT_GYR = 12 };

void ct_exp_rotvec(double wx, double wy, double wz, double *out);
void ct_strapdown_rotate(double *R, double ux, double uy, double uz, double *E);
void ct_to_nav(const double *R, double x, double y, double z, double *out);
void ct_integrate_pv(double *p, double *v, double dt, const double *a0, const double *a1);
void ct_transition_nav(double *A, int n, double dt, const double *R, double gx, double gy, double gz);

/* one inertial state's caller-owned buffers (magnetic_inertial.InsState) */
struct ct_ins {
    int n;                          /* state dimension */
    double *p, *v, *Th, *ba, *bg;   /* 3, 3, 3x3, 3, 3 */
    double *A, *P, *T;              /* n x n: transition, covariance, scratch */
    const double *Q;                /* n x n */
    double *E;                      /* 9: scratch */
};
void ct_ins_propagate(struct ct_ins *s, double dt, const double *in, double ka, double kg);

/* ----------------------------------------------------------- orientation
 * coiltrack.firmware.estimate.orientation.OrientationFilter.propagate: the composed transition
 * and noise since the last update, P <- A P A^T + Q, then Rc <- R.  theta, bias, dist: the
 * layout's row indices (estimate.layout.ORIENTATION_LAYOUT). */
struct ct_ori {
    int n, theta, bias, dist;
    double gyro_noise, gyro_bias_rw;
    const double *R;                /* 3x3, the orientation now */
    double *Rc;                     /* 3x3, the orientation at the last propagation */
    double *A, *Q, *P, *T;          /* n x n */
};
void ct_orientation_propagate(const struct ct_ori *o, double dt_acc, double dt2_acc, double cd_acc,
                              double qd_acc);

/* -------------------------------------------------------------------- lm
 * coiltrack.firmware.pose.solver._PoseFit and pose.lm.LevenbergMarquardt (k = 6): the pose fit's
 * cost with its normal equations and one damped step.  geom, B, J: the signal model's
 * (ct_signal_fields); S, w (3n): signals and weights 1 / sigma; cur (n); h (3n), H (18n): scratch;
 * p, p_t (3), R, R_t (9): the pose and the trial pose. */
struct ct_posefit {
    int n;
    const double *geom;
    double *B, *J;
    const double *S, *w, *cur;
    double *h, *H;
    double *p, *p_t, *R, *R_t;
    double step_tol;
};
/* the LM's state, in a caller-owned array st[CT_LM_NST] (the Python attributes of the same names) */
enum { CT_LM_STATE = 0, CT_LM_COST = 1, CT_LM_LAM = 2, CT_LM_IT = 3, CT_LM_CUR = 4, CT_LM_EVALS = 5,
       CT_LM_NST = 6 };
enum { CT_LM_RUNNING = 0, CT_LM_CONVERGED = 1, CT_LM_STOPPED = 2 };
struct ct_lm {
    double lam0, lam_max, cost_tol, step_sigma2;
    int iters;
    double *A[2], *g[2];            /* k x k, k: the accepted point's and the trial's normal equations */
    double *d;                      /* k: the step */
    double *st;                     /* CT_LM_NST */
};
/* a least-squares problem of pose.lm (evaluate, trial, accept, small; ctx its state), k parameters
 * (A k x k, g and d k) and linalg.damped_spd_solve(k)'s generated form */
struct ct_lm_problem {
    int k;
    void *ctx;
    double (*evaluate)(void *ctx, double *a, double *g);
    double (*trial)(void *ctx, const double *d, double *a, double *g);
    void (*accept)(void *ctx);
    int (*small)(void *ctx, const double *d);
    int (*solve)(const double *a, const double *b, double *x, double lam);
};
void ct_lm_start(const struct ct_lm *lm, const struct ct_lm_problem *pr);
int ct_lm_iterate(const struct ct_lm *lm, const struct ct_lm_problem *pr);
int ct_damped_spd_solve_6(const double *a, const double *b, double *x, double lam);   /* linalg_gen.c */
int ct_damped_spd_solve_3(const double *a, const double *b, double *x, double lam);   /* linalg_gen.c */
double ct_pose_cost(const struct ct_posefit *f, const double *p, const double *R, double *a, double *g);
int ct_pose_small(const struct ct_posefit *f, const double *d);
void ct_lm_pose_start(const struct ct_lm *lm, const struct ct_posefit *f);
int ct_lm_pose_iterate(const struct ct_lm *lm, const struct ct_posefit *f);

/* ----------------------------------------------------------------- frame
 * coiltrack.firmware.transmit.Transmitter.pose with protocol.framing.encode_frame: one POSE frame,
 * COBS-encoded and delimited, into out (at least CT_POSE_FRAME_MAX bytes), the variances clamped as
 * Transmitter.pose clamps them; returns its length, or
 * -1 for a value the wire format cannot carry (struct.pack's refusal).  v: px, py, pz, qw, qx, qy,
 * qz, then the six variances.  The schema constants are checked against protocol.schema at
 * start-up (transmit.py). */
enum { CT_POSE_ID = 48, CT_POSE_PAYLOAD = 64, CT_POSE_CRC_EXTRA = 7,
       CT_POSE_FRAME_RAW = 5 + 64 + 2, CT_POSE_FRAME_MAX = 5 + 64 + 2 + 2 + 1 };
#define CT_F32_MAX 3.0e38        /* transmit.F32_MAX: the variances are clamped to it */
int ct_cobs_encode(const uint8_t *in, int n, uint8_t *out);
/* protocol.framing.build_frame + encode_frame for a payload already in raw[5 .. 5 + len): the header
 * (len, flags 0, seq, src, id), the CRC over header and payload and the message's CRC extra, COBS
 * into out with its 0x00 delimiter; returns the encoded length (raw: room for len + 7) */
int ct_frame_seal(uint8_t *raw, int len, int seq, int src, int id, uint8_t crc_extra, uint8_t *out);
int ct_pose_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, const double *v, int64_t status,
                  int64_t quality);

/* ------------------------------------------------------------------- imu
 * coiltrack.firmware.receive: _clipped and Receiver._delta (IMU_DELTA pairs into IMU steps).  The
 * protocol constants (protocol.schema) are checked against these at start-up (receive.py). */
#define CT_IMU_CLIP 32767
#define CT_STAMP_LSB_US 8
#define CT_STAMP_MASK 16383
#define CT_STAMP_LEAD_US 16384
#define CT_STAMP_SATURATED 16384
#define CT_STAMP_DVEL 32768
#define CT_DANG_LSB_RAD 5e-5
#define CT_DVEL_LSB_MPS 1e-4
#define CT_ACC_LSB 1e-3
#define CT_GYR_LSB 5e-4
/* one node's state (receive._DeltaState), int64 each */
enum { CT_D_STAMP = 0, CT_D_X, CT_D_Y, CT_D_Z, CT_D_PENDING, CT_D_SAT, CT_D_LAST, CT_D_HAS_LAST, CT_D_AX, CT_D_AY,
       CT_D_AZ, CT_D_VX, CT_D_VY, CT_D_VZ, CT_DELTA_NST };
/* the receiver's counters and the interval start, int64 each */
enum { CT_DIO_T0 = 0, CT_DIO_UNPAIRED, CT_DIO_ANCHORS, CT_DIO_SATURATED, CT_DIO_SAT_PAIRS, CT_DIO_DELTAS, CT_DIO_N };
int ct_imu_clipped(const int64_t *v6);
int64_t ct_unwrap_stamp(int64_t stamp, int64_t now_us);
int ct_imu_delta(int64_t *st, int64_t x, int64_t y, int64_t z, int64_t s, int64_t now_us, double interval_us,
                 double step_us, double *out, int64_t *io);

#include "ct_fusimu.h"
#include "ct_fusion.h"
#include "ct_window.h"
#include "ct_ac.h"
#include "ct_rxdecode.h"
#include "ct_single_coil.h"
#include "ct_finish.h"
#include "ct_multi.h"
#include "ct_burst_open.h"
#include "ct_ahead.h"
#include "ct_solve.h"
#include "ct_acquire.h"
#include "ct_sc_policy.h"
#include "ct_sc_choose.h"
#include "ct_sc_window.h"
#include "ct_sc_close.h"
#include "ct_supervise.h"
#include "ct_report.h"
#include "ct_cov24.h"
#include "ct_fuse.h"
#include "ct_begin.h"
#include "ct_periodic.h"
#include "ct_hist_sync.h"

#ifdef __cplusplus
}
#endif


#endif /* COILTRACK_CORE_H */
