/*
 * The start of a burst's fusion update in one compiled call: the motion compensation's stages of
 * track/burst_fusion.py SensorInertial.fuse (thesis 002_cd7f1fdb7fc67471.txt sec 6.5: the pulses
 * brought to the burst's reference instant with the inertial pose history).
 *
 * Reference (the Python is the specification, followed operation by operation, same names with the
 * ct_ prefix): SensorInertial.fuse's loop over _measure_step while the stage is _COMPENSATE or
 * _COMPENSATE_PULSES, with compensate_begin and compensate_step in their compiled forms
 * (track/burst_compiled.py: ct_fusion_comp_begin, ct_fusion_pose_at, ct_fusion_comp_add) and
 * StagedSolve.predict_signals in its compiled form (pose/solver.py _predict_signals_compiled:
 * ct_signal_fields without the gradient, ct_signal_project).  What follows the compensation (the
 * re-solve's begin and steps, the filter's update) is the caller's.
 */
#ifndef CT_FUSE_H
#define CT_FUSE_H

#include <stdint.h>

/* SensorInertial's fusion stages (burst_fusion._COMPENSATE ...) */
enum { CT_FZ_COMPENSATE = 0, CT_FZ_COMPENSATE_PULSES = 1, CT_FZ_SOLVE = 2, CT_FZ_UPDATE_MAG = 5 };
/* the sensor's fusion state, a caller-owned int64 array fz[CT_FZ_N] (SensorInertial's attributes of
 * the same names): the stage, the next pulse to compensate, the compensated solve's success, the
 * bursts compensated */
enum { CT_FZ_STAGE = 0, CT_FZ_COMP_J = 1, CT_FZ_COMP_OK = 2, CT_FZ_COMPENSATED = 3, CT_FZ_N = 4 };
/* what ct_fuse_compensate stopped at: no room left in the budget (fuse returns False); the pulses
 * are all compensated (compensate_step returned 1: the caller begins the re-solve); the stage is
 * past the compensation (the caller's loop goes on) */
enum { CT_FZ_STOP = 0, CT_FZ_BEGIN = 1, CT_FZ_ON = 2 };
#define CT_FZ_MAXN 64

/* one sensor's buffers (all caller-owned, bound once): n pulses (coils), the fusion state's size
 * n_st; its signals S and the compensated S_comp (3 x n, row-major), the predicted h_ref, h_j
 * (3 x n), the poses p_ref, R_ref, p_j, R_j (3, 9), the live covariance P (n_st x n_st), the live
 * pose history (times ht, rows hd, head and count hc, capacity cap), the filter's fs (its
 * initialised flag at fs_init), the burst's t_ref (tr[0]), the pulses' mean times pulse_t (n); the
 * solver's model geometry (CT_COIL_STRIDE per coil) with its scratch B (3n), J (9n) and the
 * currents cur (n) */
struct ct_fuse {
    int n, n_st, motion_compensation, fs_init;
    double max_sigma;
    int64_t cap;
    const double *S, *P, *hd, *geom, *cur;
    double *S_comp, *h_ref, *h_j, *p_ref, *R_ref, *p_j, *R_j, *B, *J;
    const int64_t *ht, *hc, *fs, *tr, *pulse_t;
    int64_t *fz;
};

/* StagedSolve.predict_signals (compiled): out (3 x n) = R^T B_j(p) for the currents */
void ct_fuse_predict(const struct ct_fuse *z, const double *p, const double *R, double *out);
/* SensorInertial.fuse's loop while the stage is a compensation stage, within budget field
 * evaluations: the evaluations done into *used (n a prediction), *waiting as fuse sets it where it
 * stops for the budget (no room at all in this tick); returns CT_FZ_STOP, CT_FZ_BEGIN or CT_FZ_ON. */
int ct_fuse_compensate(const struct ct_fuse *z, int64_t budget, int64_t *used, int *waiting);

/* SensorInertial.on_solution of a solved burst: the solver's position (3), rotation (9) and
 * covariance (36) into the kept mag_p, mag_R, mag_C; the stage back to CT_FZ_COMPENSATE */
void ct_fuse_solution(const double *p, const double *R, const double *C, double *mag_p, double *mag_R, double *mag_C,
                      int64_t *fz);

#endif /* CT_FUSE_H */
