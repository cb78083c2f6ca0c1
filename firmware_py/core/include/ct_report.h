/*
 * A solved burst's magnetic report in one compiled call: the solution taken into the tracked pose
 * when it lies in the working volume, the POSE's quality (the motion within the burst, the
 * residual it explains), the POSE's quaternion and the covariance it is sent with (the solver's,
 * or the solver's plus the motion within the burst the IMU saw).
 *
 * References (the Python is the specification, followed operation by operation, same names with
 * the ct_ prefix): coiltrack.firmware.track.magnetic.MagneticTracker._report_pose (_take_solution,
 * PoseQuality.grade_burst, _quat, reported_covariance) and, for the fused tracker's covariance,
 * track.burst_fusion.BurstFusionTracker.reported_covariance with SensorInertial.motion_cov
 * (compensated False).  The kernels it strings together are finish.c's (ct_report_take,
 * ct_grade_burst), fusimu.c's (ct_quat_from_elements) and fusion.c's (ct_fusion_motion_cov,
 * ct_fusion_pose_at).
 */
#ifndef CT_REPORT_H
#define CT_REPORT_H

#include <stdint.h>

struct ct_quality;
/* one channel's report, all in caller-owned buffers: the quality's constants and scratch (qs), the
 * node's quality row prev (14) and motion (2: motion_m2, chi2_motion); the solver's results sp (3),
 * sR (9), scov (36); the tracked pose tp (3), tR (9); the channel's S and sigma (3 x n, row-major);
 * the pulses' start and end (n, us); the quaternion out q (4); for the motion's covariance (wl not
 * NULL): the IMU's last rate less its offset wl (3), the fusion filter's velocity v (3), the
 * burst's rms time about its middle rms_s and the covariance out cov (36) */
struct ct_report {
    const struct ct_quality *qs;
    double *prev, *motion;
    const double *sp, *sR, *scov;
    double *tp, *tR;
    const double *S, *sigma;
    const int64_t *start, *end;
    double *q;
    const double *wl, *v;
    double rms_s;
    double *cov;
};

/* MagneticTracker._report_pose's numbers for a solved burst whose middle is t_us: -1 when the
 * solution lies beyond range_m (nothing written), else the quality (PoseQuality.grade_burst with the
 * fit's cost, the NIS per dimension nis and the quiet term quiet) with the tracked pose, the
 * quaternion, the quality's row and motion and, with the motion bound, the covariance written */
int ct_report_solved(const struct ct_report *r, int64_t t_us, double cost, double nis, double quiet, double range_m,
                     int initialized);

/* PoseQuality.quiet_term over a magnetometer ring (measure.pulse.SampleRing, a KernelRing): its head and
 * count hc (hc[0], hc[1]), its samples b (cap x 3, T); ((|B| - earth) / quiet_sigma)^2 of the newest
 * sample (Ring.peek(0)), 0 when the ring is empty */
double ct_report_quiet(const int64_t *hc, const double *b, int64_t cap, double earth, double quiet_sigma);

/* Transmitter.pose_cov6's frame of a solved burst's report: the tracked position tp (3), the
 * quaternion q (4) and the diagonal of the covariance cov (36) as ct_pose_frame's values (frame.c);
 * the encoded length, or -1 where the wire format refuses a value (as ct_pose_frame) */
int ct_report_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, const double *tp, const double *q,
                    const double *cov, int64_t status, int64_t quality);

/* a fusion filter's live pose history (estimate.fusion_output.PoseHistory.live, a KernelRing): its
 * times t (cap), rows d (cap x CT_HIST_WIDTH: the position at CT_HIST_P, the rotation's nine at
 * CT_HIST_R) and head and count hc (2), read by fusion.c's ct_fusion_pose_at */
struct ct_hist {
    const int64_t *t;
    const double *d;
    const int64_t *hc;
    int64_t cap;
};

/* BurstFusionTracker.warm_start over MagneticTracker.warm_start: the solve's start into wp (3), wR (9):
 * the fusion filter's pose at t_ref (ct_fusion_pose_at over h; initialized) when the tracked pose is had (have_pose) and it
 * lies within range_m, else the tracked pose tp (3), tR (9); 0 (nothing written) before a pose */
int ct_report_warm_start(const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                         const double *tp, const double *tR, double *wp, double *wR);

/* track.ac.ACFusionTracker.warm_start over MagneticTracker.warm_start: ct_report_warm_start without the
 * range check (the fusion filter's pose at the AC block's t_ref as it is) */
int ct_report_warm_start_ac(const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, const double *tp,
                            const double *tR, double *wp, double *wR);

/* _Ahead.same: whether the n pairs of arrays (a[k], b[k], len[k] doubles each) are equal element by
 * element (C's ==, as a memoryview comparison of float64 items: NaN unequal, -0.0 equal to 0.0) */
int ct_report_same(int n, const double *const *a, const double *const *b, const int64_t *len);

#endif /* CT_REPORT_H */
