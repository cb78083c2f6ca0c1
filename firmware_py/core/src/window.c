/*
 * Pulse-window extraction: the compiled form of coiltrack.firmware.measure.pulse.PulseExtractor
 * (extract, _span_flags, _baseline_side, _pulse_moments, _amplitude) over a SampleRing's
 * caller-owned buffers (ct_sample_ring: the ring's arrays and its head and count).
 *
 * Schepers & Veltink (seeds/000_e46ec0e8bf7ea271.txt sec. 3.1): the mean of the in-pulse samples
 * but the first and the last; the earth-field baseline from the quiet samples before and after the
 * pulse (thesis seeds/002_cd7f1fdb7fc67471.txt secs. 5.2 and 5.4), fitted linearly in time and
 * evaluated at the mean in-pulse time; the variance sigma^2 / n_pulse plus the line's prediction
 * variance.  The same operations in the same order as the Python, so the same result to the bit
 * (with -ffp-contract=off): Python's float(int) is C's (double)int64 conversion, its int
 * arithmetic on times is exact in int64 for any time a stream carries.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* Ring.slot: logical index i (0 the oldest) to its slot */
int64_t ct_ring_slot(const struct ct_sample_ring *r, int64_t i)
{
    return ct_times_slot(r->cap, r->head, r->count, i);
}

/* Ring.slot over a ring's times alone: logical index i (0 the oldest) of (head, count) to its slot */
int64_t ct_times_slot(int64_t cap, int64_t head, int64_t count, int64_t i)
{
    int64_t p = head - count + i;
    if (p < 0)
        p += cap;
    else if (p >= cap)
        p -= cap;
    return p;
}

/* Ring.index_at_or_after over a ring's times t (cap; head, count): the first logical index with
 * time >= t_us (count if none); the one binary search of every ring the kernels read by time */
int64_t ct_times_index_at_or_after(const int64_t *t, int64_t cap, int64_t head, int64_t count, int64_t t_us)
{
    int64_t lo = 0, hi = count;
    while (lo < hi) {
        int64_t mid = (lo + hi) >> 1;
        if (t[ct_times_slot(cap, head, count, mid)] < t_us)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* Ring.index_at_or_after: first logical index with time >= t_us (count if none) */
int64_t ct_ring_index_at_or_after(const struct ct_sample_ring *r, int64_t t_us)
{
    return ct_times_index_at_or_after(r->t, r->cap, r->head, r->count, t_us);
}

/* the regression sums over both baseline sides (t, t^2, t x, t y, t z) and one side's result */
struct ct_side {
    int64_t n;
    double ax, ay, az;
    int sat;
};

/* PulseExtractor._span_flags */
static int64_t ct_span_flags(const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t i_lo, int64_t i_hi,
                             int64_t n)
{
    int64_t flags = CT_PULSE_OK, first, last, min_dt = 0, max_dt = 0, n_dt = 0, i, flip0 = -1;
    if (i_lo == 0 || i_hi >= n)
        flags |= CT_PULSE_INCOMPLETE;
    first = i_lo > 0 ? i_lo - 1 : i_lo;
    last = i_hi < n ? i_hi : i_hi - 1;
    if (first <= last) {
        int64_t prev_t = r->t[ct_ring_slot(r, first)];
        for (i = first + 1; i < last + 1; ++i) {
            int64_t t = r->t[ct_ring_slot(r, i)];
            int64_t dt = t - prev_t;
            if (n_dt == 0 || dt < min_dt)
                min_dt = dt;
            if (dt > max_dt)
                max_dt = dt;
            n_dt += 1;
            prev_t = t;
        }
    }
    for (i = i_lo; i < i_hi; ++i) {
        int64_t fb = r->flags[ct_ring_slot(r, i)] & CT_SAMPLE_FLIP;
        if (flip0 < 0) {
            flip0 = fb;
        } else if (fb != flip0) {
            flags |= CT_PULSE_FLIP;
            break;
        }
    }
    if (n_dt > 0) {
        if (x->max_gap_us > 0) {
            if (max_dt > x->max_gap_us)
                flags |= CT_PULSE_INCOMPLETE;
        } else if (n_dt > 1 && 2 * max_dt > 3 * min_dt) {
            flags |= CT_PULSE_INCOMPLETE;
        }
    }
    return flags;
}

/* PulseExtractor._baseline_side: samples [i0, i1) relative to ref; the regression sums go on */
static void ct_baseline_side(const struct ct_sample_ring *r, int64_t i0, int64_t i1, int64_t start,
                             const double *ref, double *sums, struct ct_side *out)
{
    double rx = ref[0], ry = ref[1], rz = ref[2];
    double st = sums[0], stt = sums[1], stx = sums[2], sty = sums[3], stz = sums[4];
    double ax = 0.0, ay = 0.0, az = 0.0;
    int64_t n = 0, i;
    int sat = 0;
    for (i = i0; i < i1; ++i) {
        int64_t p = ct_ring_slot(r, i);
        const double *b = r->b + 3 * p;
        double xx = b[0] - rx, yy = b[1] - ry, zz = b[2] - rz;
        double tr = (double)(r->t[p] - start);
        n += 1;
        ax += xx;
        ay += yy;
        az += zz;
        st += tr;
        stt += tr * tr;
        stx += tr * xx;
        sty += tr * yy;
        stz += tr * zz;
        if (r->flags[p] & CT_SAMPLE_SATURATED)
            sat = 1;
    }
    sums[0] = st;
    sums[1] = stt;
    sums[2] = stx;
    sums[3] = sty;
    sums[4] = stz;
    out->n = n;
    out->ax = ax;
    out->ay = ay;
    out->az = az;
    out->sat = sat;
}

/* PulseExtractor._pulse_moments: Welford means and co-moments of the used samples [i0, i1) into
 * pm (t, q_t, x, y, z, q_x, q_y, q_z, k_x, k_y, k_z); their times into used_t; returns the count */
static int64_t ct_pulse_moments(const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t i0, int64_t i1,
                                int64_t start, const double *ref, double *pm, int *sat_out)
{
    double rx = ref[0], ry = ref[1], rz = ref[2];
    double mt = 0.0, qt = 0.0, mx = 0.0, my = 0.0, mz = 0.0, qx = 0.0, qy = 0.0, qz = 0.0;
    double kx = 0.0, ky = 0.0, kz = 0.0;
    int64_t n_p = 0, i;
    int sat = 0;
    for (i = i0; i < i1; ++i) {
        int64_t p = ct_ring_slot(r, i);
        int64_t t = r->t[p];
        const double *b = r->b + 3 * p;
        double xx = b[0] - rx, yy = b[1] - ry, zz = b[2] - rz;
        double tr, d_t, d, np;
        if (n_p < x->max_samples)
            x->used_t[n_p] = t;
        n_p += 1;
        np = (double)n_p;
        tr = (double)(t - start);
        d_t = tr - mt;
        mt += d_t / np;
        qt += d_t * (tr - mt);
        d = xx - mx;
        mx += d / np;
        qx += d * (xx - mx);
        kx += d_t * (xx - mx);
        d = yy - my;
        my += d / np;
        qy += d * (yy - my);
        ky += d_t * (yy - my);
        d = zz - mz;
        mz += d / np;
        qz += d * (zz - mz);
        kz += d_t * (zz - mz);
        if (r->flags[p] & CT_SAMPLE_SATURATED)
            sat = 1;
    }
    pm[0] = mt;
    pm[1] = qt;
    pm[2] = mx;
    pm[3] = my;
    pm[4] = mz;
    pm[5] = qx;
    pm[6] = qy;
    pm[7] = qz;
    pm[8] = kx;
    pm[9] = ky;
    pm[10] = kz;
    *sat_out = sat;
    return n_p;
}

/* Python's max(v, 0.0): v unless 0.0 is greater (a NaN stays) */
static double ct_max0(double v)
{
    return 0.0 > v ? 0.0 : v;
}

/* PulseExtractor._amplitude */
static int64_t ct_amplitude(const struct ct_pulse *x, const struct ct_side *before, const struct ct_side *after,
                            int64_t n_p, const double *sums, const double *pm, double *amp, double *var)
{
    int64_t n_a = before->n, n_c = after->n, flags = CT_PULSE_OK;
    double ax = before->ax, ay = before->ay, az = before->az, cx = after->ax, cy = after->ay, cz = after->az;
    double st = sums[0], stt = sums[1], stx = sums[2], sty = sums[3], stz = sums[4];
    double mt = pm[0], qt = pm[1], mx = pm[2], my = pm[3], mz = pm[4], qx = pm[5], qy = pm[6], qz = pm[7];
    double kx = pm[8], ky = pm[9], kz = pm[10];
    double s2 = x->sigma * x->sigma, tm = mt, inv_nb = 1.0 / (double)(n_a + n_c);
    double bx = (ax + cx) * inv_nb, by = (ay + cy) * inv_nb, bz = (az + cz) * inv_nb, fac = inv_nb;
    double gx = 0.0, gy = 0.0, gz = 0.0, v;
    if (n_a > 0 && n_c > 0) {
        double tbar = st * inv_nb, sxx = stt - st * tbar, lim, inv_a, inv_c;
        if (sxx > 0.0) {
            double dtm = tm - tbar;
            gx = (stx - tbar * (ax + cx)) / sxx;
            gy = (sty - tbar * (ay + cy)) / sxx;
            gz = (stz - tbar * (az + cz)) / sxx;
            bx += gx * dtm;
            by += gy * dtm;
            bz += gz * dtm;
            fac = inv_nb + dtm * dtm / sxx;
        }
        lim = x->drift_limit + x->drift_nsigma * x->sigma * sqrt(1.0 / (double)n_a + 1.0 / (double)n_c);
        inv_a = 1.0 / (double)n_a;
        inv_c = 1.0 / (double)n_c;
        if (fabs(ax * inv_a - cx * inv_c) > lim || fabs(ay * inv_a - cy * inv_c) > lim ||
            fabs(az * inv_a - cz * inv_c) > lim)
            flags |= CT_PULSE_BASELINE_DRIFT;
    }
    amp[0] = mx - bx;
    amp[1] = my - by;
    amp[2] = mz - bz;
    v = s2 / (double)n_p + s2 * fac;
    var[0] = v;
    var[1] = v;
    var[2] = v;
    if (n_p >= 2) {
        double k = 1.0 / (double)((n_p - 1) * n_p);
        double *ev = x->emp_var;
        ev[0] = ct_max0(qx - 2.0 * gx * kx + gx * gx * qt) * k;
        ev[1] = ct_max0(qy - 2.0 * gy * ky + gy * gy * qt) * k;
        ev[2] = ct_max0(qz - 2.0 * gz * kz + gz * gz * qt) * k;
    }
    return flags;
}

/* PulseExtractor._fail */
static int64_t ct_pulse_fail(int64_t flags, double *amp, double *var, int64_t n_p, int64_t n_b, int64_t *out)
{
    amp[0] = amp[1] = amp[2] = 0.0;
    var[0] = var[1] = var[2] = INFINITY;
    out[0] = flags | CT_PULSE_TOO_FEW;
    out[1] = n_p;
    out[2] = n_b;
    return out[0];
}

static int64_t ct_max3(int64_t a, int64_t b, int64_t c)
{
    int64_t m = a > b ? a : b;
    return m > c ? m : c;
}

/* PulseExtractor.extract: the span's samples in its three parts (before-baseline, the used
 * in-pulse samples, after-baseline) */
int64_t ct_pulse_extract(const struct ct_pulse *x, const struct ct_sample_ring *r, int64_t start, int64_t end,
                         double *amp, double *var, int64_t *out)
{
    int64_t n = r->count, i_lo, i_hi, i_pre, used0, used1, i_post, n_p, n_b, flags, a, b;
    double sums[5] = {0.0, 0.0, 0.0, 0.0, 0.0}, pm[11], ref[3];
    struct ct_side before, after;
    int pm_sat;
    x->emp_var[0] = x->emp_var[1] = x->emp_var[2] = INFINITY;
    out[3] = 0;
    if (n == 0)
        return ct_pulse_fail(CT_PULSE_INCOMPLETE, amp, var, 0, 0, out);
    i_lo = ct_ring_index_at_or_after(r, start - x->baseline_us);
    i_hi = ct_ring_index_at_or_after(r, end + x->fall_us + x->baseline_us + 1);
    flags = ct_span_flags(x, r, i_lo, i_hi, n);
    if (i_lo == i_hi)
        return ct_pulse_fail(flags, amp, var, 0, 0, out);
    memcpy(ref, r->b + 3 * ct_ring_slot(r, i_lo), 3 * sizeof(double));   /* SampleRing.field_at */
    i_pre = ct_ring_index_at_or_after(r, start - x->guard_us + 1);
    ct_baseline_side(r, i_lo, i_pre, start, ref, sums, &before);
    used0 = ct_max3(ct_ring_index_at_or_after(r, start + x->settle_us), ct_ring_index_at_or_after(r, start) + 1,
                    i_pre);
    a = ct_ring_index_at_or_after(r, end - x->guard_us + 1);
    b = ct_ring_index_at_or_after(r, end + 1) - 1;
    used1 = a < b ? a : b;                       /* Python's min(a, b) */
    n_p = ct_pulse_moments(x, r, used0, used1, start, ref, pm, &pm_sat);
    i_post = ct_max3(ct_ring_index_at_or_after(r, end + x->fall_us), i_pre, used1 > used0 ? used1 : 0);
    ct_baseline_side(r, i_post, i_hi, start, ref, sums, &after);
    if (before.sat || after.sat || pm_sat)
        flags |= CT_PULSE_SATURATED;
    n_b = before.n + after.n;
    out[3] = n_p < x->max_samples ? n_p : x->max_samples;
    if (n_p < x->min_pulse || before.n < x->min_base || after.n < x->min_base)
        flags |= CT_PULSE_TOO_FEW;
    if (n_p == 0 || n_b == 0)
        return ct_pulse_fail(flags, amp, var, n_p, n_b, out);
    flags |= ct_amplitude(x, &before, &after, n_p, sums, pm, amp, var);
    out[0] = flags;
    out[1] = n_p;
    out[2] = n_b;
    return flags;
}

/* ------------------------------------------------------------ pose solve
 * coiltrack.firmware.pose.staged.StagedSolve._load and linalg._is_rotation, for PoseSolver's begin
 * and its results. */

/* StagedSolve._load's copy: S and sigma (3 x n) into Sv, wv ([3 j + i]), the currents into cv */
int ct_solve_load(int n, const double *S, const double *sigma, int64_t rs, int64_t cs, const double *cur,
                  int64_t cstride, double *Sv, double *wv, double *cv, double *sigma_rms)
{
    double ssum = 0.0;
    int i, j;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < n; ++j) {
            double s = S[i * rs + j * cs], sg = sigma[i * rs + j * cs];
            if (!(isfinite(s) && isfinite(sg) && sg > 0.0))
                return 0;
            Sv[3 * j + i] = s;
            wv[3 * j + i] = 1.0 / sg;
            ssum += sg * sg;
        }
    }
    for (j = 0; j < n; ++j) {
        double c = cur[j * cstride];
        if (!isfinite(c))
            return 0;
        cv[j] = c;
    }
    *sigma_rms = sqrt(ssum / (double)(3 * n));
    return 1;
}

/* linalg._is_rotation: M^T M = I to ORTHONORMAL_TOL per element and det M > 0 (0 for NaN) */
int ct_is_rotation(const double *m, double tol)
{
    double m00 = m[0], m01 = m[1], m02 = m[2], m10 = m[3], m11 = m[4], m12 = m[5], m20 = m[6], m21 = m[7];
    double m22 = m[8];
    if (!(fabs(m00 * m00 + m10 * m10 + m20 * m20 - 1.0) < tol && fabs(m01 * m01 + m11 * m11 + m21 * m21 - 1.0) < tol &&
          fabs(m02 * m02 + m12 * m12 + m22 * m22 - 1.0) < tol))
        return 0;
    if (!(fabs(m00 * m01 + m10 * m11 + m20 * m21) < tol && fabs(m00 * m02 + m10 * m12 + m20 * m22) < tol &&
          fabs(m01 * m02 + m11 * m12 + m21 * m22) < tol))
        return 0;
    return m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20) > 0.0;
}
