/*
 * A burst's solve inputs at its begin (compiled core): the or of a channel's window flags and of the
 * coil driver's faults with the POSE bits they give, and the burst's currents.
 *
 * Reference (the Python is the specification, followed operation by operation, same names with the
 * ct_ prefix): track/magnetic.py MagneticTracker._begin's first lines (measure/windows.py
 * SensorChannel.burst_flags, actuate/schedule.py PulseSchedule.any_faults, track/status.py
 * input_status, the usable test without the supervisor's veto) and MagneticTracker._prepare_currents.
 */
#ifndef CT_BEGIN_H
#define CT_BEGIN_H

#include <stdint.h>

/* the masks and bits of the Python constants (given at binding): the window flag of a saturated
 * window, the flags and faults that make a burst unusable, POSE_SATURATED, POSE_DEGRADED,
 * POSE_COIL_FAULT */
struct ct_begin_bits {
    int64_t pulse_saturated, pulse_unusable, coil_fatal, pose_saturated, pose_degraded, pose_coil_fault;
};

/* input_status(window_flags, coil_faults) */
int64_t ct_input_status(const struct ct_begin_bits *b, int64_t window_flags, int64_t coil_faults);
/* _begin's inputs: flags = or of fl (nf), faults = or of fv (nc); returns input_status's bits, with
 * *flags and *unusable (the flags' or the faults' part of the usable test) */
int64_t ct_begin_inputs(const struct ct_begin_bits *b, const int64_t *fl, int nf, const int64_t *fv, int nc,
                        int64_t *flags, int *unusable);
/* _prepare_currents: cur[j] = measured[j] where the driver reported one (non-zero), else nominal[j] */
void ct_prepare_currents(const double *measured, const double *nominal, double *cur, int n);

#endif /* CT_BEGIN_H */
