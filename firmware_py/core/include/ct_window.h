/*
 * The pulsed-DC window extraction and the pose solver's bookkeeping around its LM step: the
 * compiled form of coiltrack.firmware.measure.pulse.PulseExtractor (extract and its steps) and of
 * coiltrack.firmware.pose.solver.PoseSolver (_load, the warm-start checks, the LM units run a
 * budget at a time).  Same names (ct_ prefix), same operations in the same order.
 */
#ifndef CT_WINDOW_H
#define CT_WINDOW_H

#include <stdint.h>

/* ---------------------------------------------------------- sample ring
 * measure.pulse.SampleRing (a ring.Ring): caller-owned t (int64, cap), b (cap x 3 float64) and
 * flags (uint8, cap: bit0 saturated, bit1 flip), with the ring's head (slot of the next push)
 * and count handed in per call. */
struct ct_sample_ring {
    const int64_t *t;
    const double *b;
    const uint8_t *flags;
    int64_t cap, head, count;
};
enum { CT_SAMPLE_SATURATED = 1, CT_SAMPLE_FLIP = 2 };
enum { CT_PULSE_OK = 0, CT_PULSE_TOO_FEW = 1, CT_PULSE_SATURATED = 2, CT_PULSE_BASELINE_DRIFT = 4,
       CT_PULSE_FLIP = 8, CT_PULSE_INCOMPLETE = 16 };
int64_t ct_times_slot(int64_t cap, int64_t head, int64_t count, int64_t i);
int64_t ct_times_index_at_or_after(const int64_t *t, int64_t cap, int64_t head, int64_t count, int64_t t_us);
int64_t ct_ring_slot(const struct ct_sample_ring *r, int64_t i);
int64_t ct_ring_index_at_or_after(const struct ct_sample_ring *r, int64_t t_us);

/* PulseExtractor's settings and its caller-owned scratch: used_t (int64, max_samples), emp_var (3) */
struct ct_pulse {
    int64_t settle_us, fall_us, baseline_us, guard_us, min_pulse, min_base, max_gap_us, max_samples;
    double drift_limit, sigma, drift_nsigma;
    int64_t *used_t;
    double *emp_var;
};
/* PulseExtractor.extract: amp[3] (T), var[3] (T^2); out[0..3] = flags, n_pulse, n_base, n_rec (the
 * used times recorded); returns the flags. */
int64_t ct_pulse_extract(const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t start, int64_t end,
                         double *amp, double *var, int64_t *out);

/* ------------------------------------------------------------ pose solve
 * PoseSolver._load: S, sigma (3 x n, element (i, j) at i * rs + j * cs doubles), cur (n, stride
 * cstride) into Sv, wv (3n, [3 j + i]) and cv (n); the rms of sigma into *sigma_rms.  Returns 0
 * where a value is not finite or a sigma not positive (the Python's early return: the buffers
 * then hold what was copied before it). */
int ct_solve_load(int n, const double *S, const double *sigma, int64_t rs, int64_t cs, const double *cur,
                  int64_t cstride, double *Sv, double *wv, double *cv, double *sigma_rms);
/* linalg._is_rotation (M row-major, tol = linalg.ORTHONORMAL_TOL) */
int ct_is_rotation(const double *m, double tol);

#endif /* CT_WINDOW_H */
