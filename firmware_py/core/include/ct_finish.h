/*
 * The end of a pulsed-DC pose solve and its grading (compiled core): the solver's covariance
 * with its rotation margin and the warm-start checks, and the POSE's quality.
 *
 * References (the Python is the specification, followed operation by operation, same names with
 * the ct_ prefix):
 *   coiltrack.firmware.pose.covariance: RobustInverse6.into (_floored), RotationMargin.into;
 *   coiltrack.firmware.linalg: jacobi_eigh (jacobi_eigh_loops, _sort_eigen), spd_inverse(6),
 *     nearest_rotation;
 *   coiltrack.firmware.pose.solver.PoseSolver: _unit_finish, _warm_start_failed, _publish;
 *   coiltrack.firmware.track.quality: quality_from, PoseQuality.grade_burst (_motion, _jacobian,
 *     _remember).
 * Schepers & Veltink seeds/000_e46ec0e8bf7ea271.txt eqs 5-11 (the model and its Jacobian),
 * thesis seeds/002_cd7f1fdb7fc67471.txt sec 6.5 (the motion within a burst).
 */
#ifndef CT_FINISH_H
#define CT_FINISH_H

#include <stdint.h>

/* pose.covariance.MAX_VARIANCE (m^2 or rad^2) and EIG_FLOOR */
#define CT_MAX_VARIANCE 1e12
#define CT_EIG_FLOOR 1e-15

/* linalg.jacobi_eigh (its loops, jacobi_eigh_loops): a (n x n, overwritten), eigenvalues into w
 * (ascending), unit eigenvectors into the columns of v (n x n) */
void ct_fin_jacobi_eigh(double *a, int n, double *w, double *v, int sweeps);

/* linalg.nearest_rotation (Horn 1987 / Bar-Itzhack 2000): the proper rotation nearest m (9,
 * row-major) into out (9); m copied when it is a rotation to tol already; work: 36 doubles (the 4x4
 * K, its eigenvalues, its eigenvectors) */
#define CT_NEAREST_WORK 36
void ct_nearest_rotation(const double *m, double *out, double *work, double tol);

/* RobustInverse6 workspace: CT_ROBUST6_WORK doubles (Cholesky L, M; the Jacobi copy, V, w) */
#define CT_ROBUST6_WORK (4 * 36 + 6)
/* RobustInverse6.into: a (36, row-major, symmetric) -> cov (36) */
void ct_robust_inverse6(const double *a, double *cov, double *work);
/* RotationMargin.into: cov (36, (p, dtheta)) gets the margin in its position block */
void ct_rotation_margin(double *cov);

/* PoseSolver's warm-start checks, fixed per solve (gate, n at construction; the hemisphere per
 * begin; cbar the coils' mean centre) */
struct ct_warmcheck {
    int n;
    int check_hemi;
    double gate;
    double cbar[3];
    double hemi[3];
};
/* PoseSolver._warm_start_failed for the LM's state and cost, the fit's position p */
int ct_warm_start_failed(const struct ct_warmcheck *w, int state, double cost, const double *p);
/* PoseSolver._unit_finish's numeric part: -1 when check and the warm start failed its checks
 * (nothing written: the caller acquires); else the covariance of A into cov (RobustInverse6,
 * RotationMargin) and 1 when p and cov[0] are finite, 0 when not (SOLVE_NONFINITE) */
int ct_solve_finish(const struct ct_warmcheck *w, int check, int state, double cost, const double *p,
                    const double *A, double *cov, double *work);

/* track.quality.quality_from: round(255 e0 / (e0 + e)) */
int ct_quality_from(double var_trace_m2, double x, double scale_m, double motion_m2);

/* PoseQuality's constants and scratch: n coils of the motion term (0: none), centers (n x 3),
 * H (18 n), u (3 n), g (6), dx (6), d (n), xd (6) */
struct ct_quality {
    int n;
    int dof;
    double scale;
    double max_gap_us;
    const double *centers;
    double *H, *u, *g, *dx, *d, *xd;
};
/* PoseQuality.grade_burst: the node's previous solution prev (14: have, t_us, p, R; NULL: the node
 * has none kept), the burst's middle t_us, the fit's cost, cov (36), p (3), R (9, sensor to
 * source), S and sigma (3 x n, row-major), the pulses' start and end (n, us), the NIS per
 * dimension and the quiet term; motion[0..1] = motion_m2, chi2_motion.  Returns the quality. */
int ct_grade_burst(const struct ct_quality *qs, double *prev, int64_t t_us, double cost, const double *cov,
                   const double *p, const double *R, const double *S, const double *sigma, const int64_t *start,
                   const int64_t *end, double nis, double quiet, double *motion);

/* MagneticTracker._report's pose: when p lies within range_m of the source (track.magnetic.in_range)
 * p (3) and R (9) copied into dst_p and dst_R and 1, else 0 (nothing copied) */
int ct_report_take(const double *p, const double *R, double range_m, double *dst_p, double *dst_R);

#endif /* CT_FINISH_H */
