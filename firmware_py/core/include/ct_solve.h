/*
 * A pulsed-DC pose solve's warm path in two compiled calls: its begin (the inputs' copy and
 * checks, the hemisphere, the warm start) and a budget's run of its units (the LM's start, its
 * steps, the finish with the warm-start checks, the covariance and the published pose).
 *
 * References (the Python is the specification, followed operation by operation, same names with
 * the ct_ prefix): coiltrack.firmware.pose.solver.PoseSolver (begin, _load_hemisphere, _load_x0,
 * _unit_lm_start, _unit_lm_step, _unit_finish, _publish_pose) and pose.staged.run_units (the
 * charges); the kernels it strings together are lm.c's (ct_lm_pose_start, ct_lm_pose_iterate),
 * window.c's (ct_solve_load, ct_is_rotation) and finish.c's (ct_solve_finish,
 * ct_nearest_rotation).  The acquisition (pose.acquire, PoseSolver._start_acquisition and
 * _unit_acquire) runs in the same run through acquire.c's units where one is attached (acq);
 * without, the run stops where it is needed (CT_PH_ACQUIRE) and the Python's acquisition runs,
 * resumed at the LM's start once it is done.
 */
#ifndef CT_SOLVE_H
#define CT_SOLVE_H

#include <stdint.h>

/* the solve's phase: the unit that runs next (CT_PH_NONE: finished; CT_PH_ACQUIRE: the Python's) */
/* CT_PH_ACQ_UNITS: the compiled acquisition's units (acquire.c), where one is attached to the solve */
enum { CT_PH_NONE = 0, CT_PH_LM_START = 1, CT_PH_LM_STEPS = 2, CT_PH_FINISH = 3, CT_PH_ACQUIRE = 4,
       CT_PH_ACQ_UNITS = 5 };

/* the solve's state and results, a caller-owned array st[CT_SV_NST] (the Python attributes of the
 * same names): the phase, the results (status flags of pose.solver, iterations, cost, converged),
 * the warm start and reacquisition flags, the rms of sigma, the hemisphere check (check_hemi,
 * hx, hy, hz), the units charged and evaluations done by the last run */
enum { CT_SV_PHASE = 0, CT_SV_STATUS = 1, CT_SV_ITERATIONS = 2, CT_SV_COST = 3, CT_SV_CONVERGED = 4,
       CT_SV_WARM = 5, CT_SV_REACQUIRED = 6, CT_SV_SIGMA_RMS = 7, CT_SV_CHECK_HEMI = 8, CT_SV_HEMI = 9,
       CT_SV_SPENT = 12, CT_SV_EVALS = 13, CT_SV_NST = 14 };

/* pose.solver's status flags */
enum { CT_SOLVE_OK = 0, CT_SOLVE_BAD_INPUT = 1, CT_SOLVE_NO_START = 2, CT_SOLVE_NOT_CONVERGED = 4,
       CT_SOLVE_NONFINITE = 8, CT_SOLVE_RUNNING = 16, CT_SOLVE_REACQUIRED = 32 };

struct ct_posefit;
struct ct_lm;
struct ct_acquire;
/* one solver's parts, all in caller-owned buffers: its fit and LM (lm.c), the warm-start checks'
 * constants (n, gate, cbar; finish.c), the results' covariance (36), rotation (9) and position
 * (3), the scratch m9 (9) and work (CT_ROBUST6_WORK, at least CT_NEAREST_WORK), the state st */
struct ct_solve {
    const struct ct_posefit *f;
    const struct ct_lm *lm;
    int n;
    double gate;
    double cbar[3];
    double tol;                  /* linalg.ORTHONORMAL_TOL */
    double *cov, *rot, *pos, *m9, *work, *st;
    const struct ct_acquire *acq;  /* the compiled acquisition (its S, cur: f's), or NULL: the Python's */
};

/* PoseSolver.begin: S, sigma (3 x n, element (i, j) at i * rs + j * cs), cur (n, stride cstride),
 * the hemisphere (3, or NULL), the warm start x0p (3) and x0R (9, row-major; both NULL: cold).
 * Returns CT_SOLVE_BAD_INPUT (phase CT_PH_NONE) or CT_SOLVE_RUNNING with the phase CT_PH_LM_START
 * (warm), CT_PH_ACQ_UNITS (cold, the acquisition begun) or, without acq, CT_PH_ACQUIRE (cold: the
 * caller begins the acquisition). */
int ct_solve_begin(const struct ct_solve *s, const double *S, const double *sigma, int64_t rs, int64_t cs,
                   const double *cur, int64_t cstride, const double *hemi, const double *x0p, const double *x0R);
/* staged.run_units over the compiled units from *spent (units charged so far in this step) within
 * budget, each charged n: runs while the phase is the acquisition's units, the LM's start, its steps
 * or the finish and the next unit fits (the first of a step always runs); *spent grows by the
 * charges.  Returns the phase it stopped at (the budget is spent; CT_PH_NONE: finished, with
 * CT_SOLVE_NO_START in the status where the acquisition found no start). */
int ct_solve_run(const struct ct_solve *s, int64_t *spent, int64_t budget);

#endif /* CT_SOLVE_H */
