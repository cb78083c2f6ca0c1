/*
 * A pose solve's acquisition (a start pose from one signal matrix, no prior), staged into units of
 * at most n field evaluations each charged n: Kuipers' closed form on S M^+ (thesis
 * seeds/002_cd7f1fdb7fc67471.txt App. 5.A, eqs 5.9-5.34), with the exact model near the source the
 * position fit on the rotation invariant U = S^T S (the LM of lm.c, 3 parameters), a grid of
 * directions scored by the misfit of U where that fit misses its noise level, and the orientation
 * from the polar factor of B(p) S^T.
 *
 * References (the Python is the specification, followed operation by operation, same names with
 * the ct_ prefix): coiltrack.firmware.pose.acquire._Kuipers (pseudo_inverse, position, rotation)
 * and Acquisition (begin, _unit_moments, _unit_kuipers_position, _unit_kuipers_rotation,
 * _invariants, _unit_refine_start, _unit_refine_step, _refined, _start_grid, _seek_direction,
 * _unit_radius, _unit_misfit, _trace_at, _misfit_at, _keep_candidate, _next_candidate,
 * _unit_orient, evaluate, trial, accept, small, _invariant_residual); the kernels it strings
 * together are signal.c's (ct_signal_fields), finish.c's (ct_fin_jacobi_eigh,
 * ct_nearest_rotation), ekf.c's (ct_spd_inverse) and lm.c's (ct_lm_start, ct_lm_iterate with
 * linalg_gen.c's ct_damped_spd_solve_3).
 */
#ifndef CT_ACQUIRE_H
#define CT_ACQUIRE_H

#include <stdint.h>

/* pose.acquire.GRID_DIRECTIONS, GRID_CANDIDATES and _INV_ITERS, the invariant LM's settings */
#define CT_AQ_GRID_DIRECTIONS 512
#define CT_AQ_GRID_CANDIDATES 3
#define CT_AQ_INV_ITERS 15

/* the next unit (Acquisition.next_unit): CT_AQ_NONE when finished */
enum { CT_AQ_NONE = 0, CT_AQ_MOMENTS = 1, CT_AQ_KUIPERS_POSITION = 2, CT_AQ_KUIPERS_ROTATION = 3,
       CT_AQ_REFINE_START = 4, CT_AQ_REFINE_STEP = 5, CT_AQ_RADIUS = 6, CT_AQ_MISFIT = 7, CT_AQ_ORIENT = 8 };

/* the acquisition's state, a caller-owned array st[CT_AQ_NST] (the Python attributes of the same
 * names): the next unit, ok, the hemisphere _h (3), _sigma_rms, _tr, _tol, _best_m, _k, _rad,
 * _rstep, _r0, _cand, Kuipers' _u (3) and _k, the field evaluations done (counted, never reset) */
enum { CT_AQ_UNIT = 0, CT_AQ_OK = 1, CT_AQ_H = 2, CT_AQ_SIGMA_RMS = 5, CT_AQ_TR = 6, CT_AQ_TOL = 7,
       CT_AQ_BEST_M = 8, CT_AQ_K = 9, CT_AQ_RAD = 10, CT_AQ_RSTEP = 11, CT_AQ_R0 = 12, CT_AQ_CAND = 13,
       CT_AQ_KU = 14, CT_AQ_KK = 17, CT_AQ_EVALS = 18, CT_AQ_NST = 19 };

/* the scratch, a caller-owned array work[CT_AQ_WORK_FIXED + n * n + 3 * n]: Kuipers' G, W, V, w, L
 * (and ct_spd_inverse's second factor M), S3; the orientation's M; the invariant fit's point ip,
 * trial tp and best point; the grid's candidates; the 3-parameter LM's A0, g0, A1, g1, d and state;
 * ct_nearest_rotation's work; then U (n x n) and M^+ (n x 3) */
enum { CT_AQW_G = 0, CT_AQW_W = 9, CT_AQW_V = 18, CT_AQW_WV = 27, CT_AQW_L = 30, CT_AQW_LM = 39, CT_AQW_S3 = 48,
       CT_AQW_MO = 57, CT_AQW_IP = 66, CT_AQW_TP = 69, CT_AQW_BEST = 72, CT_AQW_CAND_P = 75, CT_AQW_CAND_M = 84,
       CT_AQW_A0 = 87, CT_AQW_G0 = 96, CT_AQW_A1 = 99, CT_AQW_G1 = 108, CT_AQW_D = 111, CT_AQW_LMST = 114,
       CT_AQW_NEAR = 120, CT_AQ_WORK_FIXED = 156 };

struct ct_lm;
/* one acquisition's parts, all in caller-owned buffers: the signal model's geometry and its B (3n),
 * J (9n) (ct_signal_fields), the solver's signals S (3n, layout [3 j + i]) and currents cur (n),
 * the grid (pose.acquire.fibonacci_directions, 3 x CT_AQ_GRID_DIRECTIONS), the start p (3), R (9),
 * the scratch and the state; the coils' mean centre cbar, the near field's range near
 * (Acquisition.near), mu0 / 4 pi and linalg.ORTHONORMAL_TOL; lm: the invariant fit's LM over the
 * scratch (ct_acquire_bind) */
struct ct_acquire {
    int n;
    const double *geom;
    double *B, *J;
    const double *S, *cur, *grid;
    double *p, *R, *work, *st;
    double cbar[3];
    double near, mu0_4pi, tol;
    struct ct_lm *lm;
};

/* the invariant fit's LM (pose.lm.LevenbergMarquardt(3, 1e-3, 1e8, _INV_ITERS, 0.0)) over a's
 * scratch, into lm (caller-owned, kept with a) */
void ct_acquire_bind(struct ct_acquire *a, struct ct_lm *lm);
/* Acquisition.begin: the hemisphere (hx, hy, hz) and sigma's rms; the next unit CT_AQ_MOMENTS */
void ct_acquire_begin(const struct ct_acquire *a, double hx, double hy, double hz, double sigma_rms);
/* Acquisition.next_unit(): runs the next unit (at most n evaluations, counted in st[CT_AQ_EVALS]);
 * returns the unit after it (CT_AQ_NONE: finished, ok in st[CT_AQ_OK], the start in p, R) */
int ct_acquire_unit(const struct ct_acquire *a);

#endif /* CT_ACQUIRE_H */
