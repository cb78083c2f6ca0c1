/*
 * A solved burst's magnetic report in one compiled call: see include/ct_report.h.  Each function
 * follows the Python named beside it operation by operation (-ffp-contract=off), so the pose, the
 * quality, the quaternion and the covariance are the reference's to the bit
 * (tests/firmware/core/test_core_report_chain.py).
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

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
        ct_fusion_motion_cov(r->scov, r->cov, r->sp, 0, initialized, r->rms_s * r->rms_s, NULL, 0, r->v, r->wl);
    return q;
}

int ct_report_warm_start(const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                         const double *tp, const double *tR, double *wp, double *wR)
{
    if (!have_pose)
        return 0;
    if (h != NULL && initialized && ct_fusion_pose_at(h->t, h->d, h->cap, h->hc[0], h->hc[1], t_ref, wp, wR) &&
        sqrt(wp[0] * wp[0] + wp[1] * wp[1] + wp[2] * wp[2]) <= range_m)
        return 1;
    memcpy(wp, tp, 3 * sizeof(double));
    memcpy(wR, tR, 9 * sizeof(double));
    return 1;
}

int ct_report_warm_start_ac(const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, const double *tp,
                            const double *tR, double *wp, double *wR)
{
    if (!have_pose)
        return 0;
    if (h != NULL && initialized && ct_fusion_pose_at(h->t, h->d, h->cap, h->hc[0], h->hc[1], t_ref, wp, wR))
        return 1;
    memcpy(wp, tp, 3 * sizeof(double));
    memcpy(wR, tR, 9 * sizeof(double));
    return 1;
}

int ct_report_same(int n, const double *const *a, const double *const *b, const int64_t *len)
{
    int k;
    int64_t i;
    for (k = 0; k < n; ++k)
        for (i = 0; i < len[k]; ++i)
            if (a[k][i] != b[k][i])
                return 0;
    return 1;
}

double ct_report_quiet(const int64_t *hc, const double *b, int64_t cap, double earth, double quiet_sigma)
{
    int64_t p;
    double m, z;
    if (hc[1] < 1)
        return 0.0;                                 /* Ring.peek(0): -1, nothing held */
    p = hc[0] - 1;
    if (p < 0)
        p += cap;
    p *= 3;
    m = sqrt(b[p] * b[p] + b[p + 1] * b[p + 1] + b[p + 2] * b[p + 2]);
    z = (m - earth) / quiet_sigma;
    return z * z;
}

int ct_report_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, const double *tp, const double *q,
                    const double *cov, int64_t status, int64_t quality)
{
    double v[13];
    int k;
    v[0] = tp[0];
    v[1] = tp[1];
    v[2] = tp[2];
    v[3] = q[0];
    v[4] = q[1];
    v[5] = q[2];
    v[6] = q[3];
    for (k = 0; k < 6; ++k)
        v[7 + k] = cov[7 * k];
    return ct_pose_frame(out, seq, src, node, t_us, v, status, quality);
}
