/*
 * A solved burst's magnetic report in one compiled call: see include/ct_report.h.  Each function
 * follows the Python named beside it operation by operation (-ffp-contract=off), so the pose, the
 * quality, the quaternion and the covariance are the reference's to the bit
 * (tests/firmware/core/test_core_report_chain.py).
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* SensorInertial.motion_cov with compensated False */
void ct_report_motion_cov(const double *C, const double *p, const double *wl, const double *v, int initialized,
                          double rms_s, double *out)
{
    const double tr2 = rms_s * rms_s;
    double ao, ap;
    int i;
    memcpy(out, C, 36 * sizeof(double));
    ao = (wl[0] * wl[0] + wl[1] * wl[1] + wl[2] * wl[2]) * tr2;
    ap = initialized ? (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * tr2 : 0.0;
    ap += (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) * ao;
    for (i = 0; i < 3; ++i) {
        out[7 * i] += ap;
        out[7 * (3 + i)] += ao;
    }
}

/* MagneticTracker._report_pose: _take_solution, PoseQuality.grade_burst, _quat, reported_covariance */
int ct_report_solved(const struct ct_report *r, int64_t t_us, double cost, double nis, double quiet, double range_m,
                     int initialized)
{
    int q;
    if (!ct_report_take(r->sp, r->sR, range_m, r->tp, r->tR))
        return -1;
    q = ct_grade_burst(r->qs, r->prev, t_us, cost, r->scov, r->tp, r->tR, r->S, r->sigma, r->start, r->end, nis,
                       quiet, r->motion);
    ct_quat_from_elements(r->tR, r->q);
    if (r->wl != NULL)
        ct_report_motion_cov(r->scov, r->sp, r->wl, r->v, initialized, r->rms_s, r->cov);
    return q;
}
