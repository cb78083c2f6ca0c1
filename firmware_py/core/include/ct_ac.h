/*
 * coiltrack compiled core, AC excitation (Raab et al. 1979, seeds/004_86267342cd7488ce.txt):
 * the synchronous demodulation of coiltrack.firmware.measure.demod.Demodulator (src/demod.c)
 * and one update of Raab's iterative tracker, coiltrack.firmware.pose.raab_update and
 * raab_correction (src/raab.c).  The Python functions are the reference: same names with the
 * ct_ prefix, the same floating-point operations in the same order.
 */
#ifndef CT_AC_H
#define CT_AC_H

#include <stdint.h>

/* ------------------------------------------------------------------ demod
 * The demodulator's integer state, an int64 array st[CT_DM_NST] (Demodulator._st). */
enum { CT_DM_T0 = 0, CT_DM_REF = 1, CT_DM_NEXT_K = 2, CT_DM_LAST_T = 3, CT_DM_STARTED = 4, CT_DM_CURSOR = 5,
       CT_DM_PENDING = 6, CT_DM_BLOCK_K = 7, CT_DM_BLOCK_FLAGS = 8, CT_DM_BLOCK_SAMPLES = 9, CT_DM_NST = 10 };
/* its results besides S, Q, var, qvar, dc: a float64 array out[CT_DMO_N] */
enum { CT_DMO_RESID = 0, CT_DMO_SIGNAL_CHI2 = 1, CT_DMO_QUAD_CHI2 = 2, CT_DMO_QUAD_RATIO = 3, CT_DMO_N = 4 };
/* measure.pulse's flag bits the demodulator sets (CT_PULSE_*, CT_SAMPLE_*): ct_window.h */

/* one demodulator's caller-owned buffers (n coils, p = 2 + 2 n unknowns, `slots` block accumulators) */
struct ct_demod {
    int n, p, slots;
    int64_t window_us, hop_us;
    double sigma2;
    const double *freqs;            /* n */
    const double *h;                /* 2 n: the magnetometer's response (re, im) per coil */
    double *cph, *sph;              /* n: cos, sin of the current phases */
    double *G, *R, *BB;             /* slots x p p, slots x 3 p, slots x 3 */
    int64_t *count, *flags, *kslot; /* slots */
    double *phi;                    /* p */
    double *Gf, *L, *Ginv, *x, *b, *X;  /* p p, p p, p p, p, p, 3 p: a block's solve */
    double *S, *Q, *var, *qvar, *dc;    /* 3 n, 3 n, 3 n, n, 3 */
    int64_t *st;                    /* CT_DM_NST */
    double *out;                    /* CT_DMO_N */
};

/* Demodulator.push: one sample; returns the block it completes, or -1 */
int64_t ct_demod_push(const struct ct_demod *d, int64_t t, double bx, double by, double bz, int64_t sample_flags);
/* Demodulator.feed over a measure.pulse.SampleRing (times rt, fields rb (cap x 3), flags rf; `count`
 * entries, the newest in slot `last`): the samples after the cursor, at most `left`, up to the first that
 * completes a block (then st[CT_DM_PENDING] = its index); returns 1 when one did, else 0 */
int ct_demod_feed(const struct ct_demod *d, const int64_t *rt, const double *rb, const uint8_t *rf, int64_t cap,
                  int64_t count, int64_t last, int64_t left);
/* Demodulator.step's result bits */
enum { CT_DMS_FINISHED = 1, CT_DMS_SOLVED = 2, CT_DMS_NO_SIGNAL = 4, CT_DMS_DISTORTED = 8 };
/* Demodulator.step: one tick of a channel: the block the last feed completed solved at the drive's
 * current phases `phase` (n) of now, with its gates (signal_chi2 below signal_gate: flagged
 * CT_PULSE_TOO_FEW; quadrature_ratio above ratio_max and quadrature_chi2 above q_gate: distorted),
 * else ct_demod_feed over the ring; returns the CT_DMS_* bits (0: fed) */
int ct_demod_step(const struct ct_demod *d, const double *phase, const int64_t *rt, const double *rb,
                  const uint8_t *rf, int64_t cap, int64_t count, int64_t last, int64_t left, double signal_gate,
                  double ratio_max, double q_gate);
/* Demodulator.finish: solve block k; 1 when solved (then also signal_chi2, quadrature_chi2 and
 * quadrature_ratio into out) */
int ct_demod_finish(const struct ct_demod *d, int64_t k);

/* ------------------------------------------------------------------- raab
 * One update of Raab's tracker (pose.raab.RaabTracker._unit_update through pose.raab_update.Update):
 * the exact-loop correction (raab_correction.LoopCorrection.correct, or none), F = S_c M^+ and
 * k = |F|_F / sqrt(3/2) (coupling), the detection (detect: eqs 7, 11, 21-26), the preconditioner's
 * solve (precondition_step: linalg.lu_solve), the clip (Fig. 8), the frame conversion and the update
 * by addition (orientation_update, position_update: eqs 27-31) and R = A^T (dcm, Table II).
 * The constants, from the Python modules at binding: */
enum { CT_RP_C = 0, CT_RP_POLE_COS = 1, CT_RP_MAX_STEP = 2, CT_RP_LIN_MAX = 3, CT_RP_LIN_STEP = 4,
       CT_RP_ACQUIRED_STEP = 5, CT_RP_N = 6 };
/* the update's results: the clipped steps (d_alpha0, d_beta0, d_rho, d_psi0, d_theta0, d_phi0), k,
 * and 1.0 when the unclipped angle steps were all below CT_RP_ACQUIRED_STEP */
enum { CT_RO_DA0 = 0, CT_RO_DB0 = 1, CT_RO_DRHO = 2, CT_RO_DPSI0 = 3, CT_RO_DTH0 = 4, CT_RO_DPHI0 = 5, CT_RO_K = 6,
       CT_RO_ACQUIRED = 7, CT_RO_N = 8 };
/* the return bits of ct_raab_update */
enum { CT_RAAB_OK = 1, CT_RAAB_LIN_DROPPED = 2 };

struct ct_raab {
    int n;
    int corr;                       /* 1: the exact-loop correction (b, G, K, perm), 0: none */
    const double *par;              /* CT_RP_N */
    const double *cbar;             /* 3: the coil centres' centroid */
    const double *S, *mp, *cur;     /* 3 n signals [3 j + i], M^+ [3 j + c], n currents */
    double *Sc, *F;                 /* 3 n corrected signals, 9 coupling */
    double *x;                      /* 6: alpha, beta, rho, psi, theta, phi */
    double *R;                      /* 9: R = A^T (sensor -> source), row-major */
    const double *pm;               /* 3: the point of the last evaluation */
    const double *b, *G;            /* 3 n, 9 n: the correction per ampere and its gradient */
    const double *K;                /* 36: K's LU factors */
    const int64_t *perm;            /* 6 */
    double *out;                    /* CT_RO_N */
};

/* returns CT_RAAB_OK (bit) when k > 0 and finite (then the update is done), and CT_RAAB_LIN_DROPPED
 * when the correction's linear term was dropped (the estimate beyond CT_RP_LIN_MAX x range of pm) */
int ct_raab_update(const struct ct_raab *r, int lin, int k_id);
/* RaabTracker._coupling (pose.raab, through raab_update.Update.couple): the first part of ct_raab_update, the
 * corrected signals, F and k (into out[CT_RO_K]); returns CT_RAAB_LIN_DROPPED as ct_raab_update */
int ct_raab_coupling(const struct ct_raab *r);
/* raab_update.moment_pseudo_inverse (n coils, moments per ampere mpa (3 n), currents cur (n)): the moments into
 * mom (3 n) and M^+ into mp (3 n); 0 when the moments do not span 3-D */
int ct_raab_pseudo_inverse(int n, const double *mpa, const double *cur, double *mom, double *mp);

/* raab_correction.LoopCorrection's refresh and preconditioner: its buffers b (3 n), G (9 n), K (36), perm (6) */
struct ct_raab_corr {
    int n;
    double c_raab;                  /* C of eq 3 (model.field.MU0_2PI) */
    double *b, *G, *K;
    int64_t *perm;
};
/* LoopCorrection.refresh: b, G from the exact model's fields Bv (3 n) and gradients Jv (9 n) per ampere at the
 * estimate x and Raab's dipole of the moments per ampere mpa (model.field.dipole_polar); out[0] = rel, out[1] =
 * the shift against the last correction's linear term moved by dd (3) in the noise (weights w, currents cur)
 * when shift_ok, else 0 */
void ct_raab_refresh(const struct ct_raab_corr *c, const double *x, const double *Bv, const double *Jv,
                     const double *mpa, const double *w, const double *cur, const double *dd, int shift_ok,
                     double *out);
/* LoopCorrection.precondition: K = I + G D T at x (M^+ mp, currents cur, k = C / rho^3) and its LU factors
 * (linalg.lu_factor); returns 1 when factored */
int ct_raab_precondition(const struct ct_raab_corr *c, const double *x, const double *mp, const double *cur, double k);

/* ------------------------------------------------------------- raab_cov
 * The covariance of Raab's tracker, pose.raab_covariance.RaabCovariance (src/raab_cov.c).
 * Its constants, from the Python modules at binding: */
enum { CT_RCP_COV_TOL = 0, CT_RCP_CARRY_MAX = 1, CT_RCP_Q_TOL = 2, CT_RCP_ISO_TOL = 3, CT_RCP_MAX_VARIANCE = 4,
       CT_RCP_EIG_FLOOR = 5, CT_RCP_N = 6 };
/* its state besides the buffers: C_s formed (1.0) or not, and the published sigmas */
enum { CT_RCS_CS_OK = 0, CT_RCS_SIG_P = 1, CT_RCS_SIG_O = 2, CT_RCS_N = 3 };

struct ct_raab_cov {
    int n;
    const double *par;              /* CT_RCP_N */
    const double *cbar;             /* 3: the coil centres' centroid */
    double *cov;                    /* 36: the published covariance of (p, dtheta) */
    double *K, *H;                  /* 18 n each: rows [J_j | [B_j]x] per A, source and sensor frame */
    double *q, *qm;                 /* 3 n weights x currents of a formation, n those of C_s */
    double *A, *Cs, *pc;            /* 36 information, 36 C_s, 3 where C_s was formed */
    double *st;                     /* CT_RCS_N */
    double *T, *L, *M;              /* 36 each: scratch */
};

/* RaabCovariance.rows: the rows [J_j | [B_j]x] of the fields Bv (3 n) and gradients Jv (9 n) per ampere */
void ct_raab_cov_rows(const struct ct_raab_cov *c, const double *Bv, const double *Jv);
/* RaabCovariance.publish at the estimate x (6, Raab's coordinates; R (9) row-major), weights w (3 n), currents
 * cur (n), the last evaluation at pm (3), rel; returns 1 when published, 0 (nothing changed) where the robust
 * inverse needs its eigenvalue floor (pose.covariance.RobustInverse6._floored) or the reference would divide
 * by zero: the caller then runs the reference */
int ct_raab_cov_publish(const struct ct_raab_cov *c, const double *x, const double *R, const double *w,
                        const double *cur, const double *pm, double rel);


/* ----------------------------------------------------------- raab begin
 * pose.raab_io.RaabIO.load: a solve's inputs into the tracker's buffers: the signals, their
 * weights 1/sigma and the currents (StagedSolve._load), the hemisphere (_load_hemisphere), the warm
 * start's rotation and Raab's angles of its position (_load_x0: raab_update.is_rotation,
 * load_rotation, angles_from_pose) and the moments with M^+ (moment_pseudo_inverse). */
struct ct_raab_io {
    int n;
    double tol;                     /* raab_update._ORTHO_TOL */
    double c_raab;                  /* C of eq 3 (model.field.MU0_2PI) */
    const double *cbar;             /* 3 */
    double *Sv, *wv, *cur;          /* 3 n, 3 n, n */
    double *sigma_rms;              /* 1 */
    double *hemi;                   /* 3 */
    double *m9, *R, *x;             /* 9 (the warm start's matrix), 9 (R = A^T), 6 (alpha ... phi) */
    const double *mpa;              /* 3 n: moments per ampere */
    double *mom, *mp;               /* 3 n, 3 n */
    const double *Sc;               /* 3 n: the corrected signals (residual_cost) */
    const double *pm;               /* 3: the point of the last evaluation (moved) */
    const double *acq_hemi;         /* 3: the acquisition's hemisphere (behind) */
    double margin;                  /* behind: pose.raab._HEMI_MARGIN */
    double *position, *rotation, *angles;   /* 3, 9, 6: the published pose (RaabTracker._finish) */
};
/* its results: the first check that failed, or where the caller goes on */
enum { CT_RIN_BAD_LOAD = 0, CT_RIN_BAD_HEMI = 1, CT_RIN_BAD_X0 = 2, CT_RIN_PROJECT = 3, CT_RIN_NO_START = 4,
       CT_RIN_OK = 5 };
/* S, sigma (3 x n at row and column strides rs, cs), cur (n at cstride); hemi (3) or NULL; x0p (3) and
 * x0R (9, row-major) or NULL, x0_pair 0 when exactly one of them was given. CT_RIN_PROJECT: the warm
 * start's matrix (in m9) is no rotation to tol: the caller projects it (linalg.nearest_rotation) and
 * goes on with angles_from_pose and the pseudo-inverse */
int ct_raab_inputs(const struct ct_raab_io *in, const double *S, const double *sigma, int64_t rs, int64_t cs,
                   const double *cur, int64_t cstride, const double *hemi, const double *x0p, const double *x0R,
                   int x0_pair);
int ct_raab_is_rotation(const double *m, double tol);
/* raab_update.residual_cost of the corrected signals Sc with the weights wv at the estimate x, R */
double ct_raab_residual_cost(const struct ct_raab_io *io);
/* RaabTracker._finish's pose: position = point(x, cbar), R = A^T of x's angles (sync_rotation), rotation
 * = R, angles = x; 1 when the position is finite */
int ct_raab_finish_pose(const struct ct_raab_io *io);
/* RaabIO.moved: the estimate's point more than refresh x range from pm */
int ct_raab_moved(const struct ct_raab_io *io, double refresh);
/* RaabIO.behind: the estimate's direction more than margin behind the hemisphere (the acquisition's when
 * acquiring, else the last begin's) */
int ct_raab_behind(const struct ct_raab_io *io, int acquiring);
void ct_raab_angles_from_pose(double px, double py, double pz, const double *R, double *x);

/* ------------------------------------------------------------- ac_blocks
 * The measure stage of AC excitation, measure.ac_blocks.ACBlockMeasurement._tick (src/ac_blocks.c): each
 * channel's Demodulator.step (ct_demod_step) with the solved block's bookkeeping (_feed), then the
 * block handed to the tracker when every channel has solved it (_assemble: PulseSchedule.ac_block,
 * SensorChannel.load_block's copies, the sums).  The integer state, an int64 array st[CT_ACB_NST]
 * (ACBlockMeasurement._st), and the float one fs[CT_ACBF_N] (_fs): */
enum { CT_ACB_BLOCK_K = 0, CT_ACB_COMPLETE = 1, CT_ACB_T_REF = 2, CT_ACB_BLOCKS = 3, CT_ACB_SKIPPED = 4,
       CT_ACB_BAD = 5, CT_ACB_DISTORTED = 6, CT_ACB_NO_SIGNAL = 7, CT_ACB_MAX_SAMPLES = 8, CT_ACB_NST = 9 };
enum { CT_ACBF_QUAD_SUM = 0, CT_ACBF_QUAD_MAX = 1, CT_ACBF_RESID_SUM = 2, CT_ACBF_SIGNAL_GATE = 3,
       CT_ACBF_RATIO_MAX = 4, CT_ACBF_Q_GATE = 5, CT_ACBF_N = 6 };
/* at most this many channels (a bit of ct_ac_blocks_step's result each) */
#define CT_ACB_MAX_CH 48

/* one channel: its demodulator, its sample ring and its burst's arrays (SensorChannel) */
struct ct_ac_channel {
    const struct ct_demod *dm;
    const int64_t *rt;              /* the ring's times, fields (cap x 3) and flags */
    const double *rb;
    const uint8_t *rf;
    int64_t cap;
    double *S, *var;                /* 3 n each, row-major (3, n) */
    int64_t *flags, *pulse_mid;     /* n each */
    uint8_t *done;                  /* n (numpy bool) */
};

struct ct_ac_blocks {
    int nch, n;
    const struct ct_ac_channel *ch; /* nch */
    const double *phase;            /* n: the drive's measured current phases (the actuation's) */
    const double *amplitude;        /* n: its measured amplitudes */
    int64_t *sched_start, *sched_end;   /* n: PulseSchedule.start, end */
    double *sched_measured;         /* n: PulseSchedule.measured */
    int64_t *solved_k, *distorted;  /* nch */
    double *quad_ratio;             /* nch */
    int64_t *st;                    /* CT_ACB_NST */
    double *fs;                     /* CT_ACBF_N */
};

/* ACBlockMeasurement._tick: `rs` (2 nch) each channel's ring count and last pushed slot; returns bit 0 when
 * a block was handed over (_assemble: the channels' bursts loaded), bit 1 + i when channel i solved a block
 * whose DC term goes into its earth ring (done by the caller) */
int64_t ct_ac_blocks_step(const struct ct_ac_blocks *a, const int64_t *rs);

#endif /* CT_AC_H */
