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

/* Ring.index_at_or_after: the first logical index whose time is >= t_us (count if none) */
static int64_t hist_index_at_or_after(const struct ct_hist *h, int64_t t_us)
{
    int64_t lo = 0, hi = h->hc[1], mid, p;
    const int64_t base = h->hc[0] - h->hc[1];
    while (lo < hi) {
        mid = (lo + hi) >> 1;
        p = base + mid;
        if (p < 0)
            p += h->cap;
        else if (p >= h->cap)
            p -= h->cap;
        if (h->t[p] < t_us)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* Ring.slot */
static int64_t hist_slot(const struct ct_hist *h, int64_t i)
{
    int64_t p = h->hc[0] - h->hc[1] + i;
    if (p < 0)
        p += h->cap;
    else if (p >= h->cap)
        p -= h->cap;
    return p;
}

int ct_report_pose_at(const struct ct_hist *h, int64_t t_us, double *out_p, double *out_R)
{
    const int64_t n = h->hc[1];
    int64_t i, prev, k, t0, tk;
    const double *dp, *dk;
    double a, b;
    int c;
    if (n < 2)
        return 0;
    i = hist_index_at_or_after(h, t_us);
    if (i >= n)
        return 0;
    if (i == 0) {
        if (h->t[hist_slot(h, 0)] != t_us)
            return 0;
        i = 1;
    }
    prev = hist_slot(h, i - 1);
    k = hist_slot(h, i);
    t0 = h->t[prev];
    tk = h->t[k];
    /* Python's int / int: the exact quotient rounded once, as the doubles' (exact below 2^53) */
    a = tk > t0 ? (double)(t_us - t0) / (double)(tk - t0) : 1.0;
    b = 1.0 - a;
    dp = h->d + prev * h->width;
    dk = h->d + k * h->width;
    for (c = 0; c < 3; ++c)
        out_p[c] = b * dp[c] + a * dk[c];
    for (c = 0; c < 9; ++c)
        out_R[c] = b * dp[3 + c] + a * dk[3 + c];
    return 1;
}

int ct_report_warm_start(const struct ct_hist *h, int64_t t_ref, int have_pose, int initialized, double range_m,
                         const double *tp, const double *tR, double *wp, double *wR)
{
    if (!have_pose)
        return 0;
    if (h != NULL && initialized && ct_report_pose_at(h, t_ref, wp, wR) &&
        sqrt(wp[0] * wp[0] + wp[1] * wp[1] + wp[2] * wp[2]) <= range_m)
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
