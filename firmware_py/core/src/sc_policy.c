/*
 * The adaptive single-coil policy's numeric parts: the fixed cycle's reference covariance
 * (actuate/accuracy.py, accuracy_budget.py), the eq-4 update of a pulse in flight
 * (coil_choice.PoseCovUpdate) and the magnetometer-range current limits
 * (single_coil_policy._decide_limits, coil_choice.saturation_current_limit); see ct_sc_policy.h.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* FixedCycleReference._propagate (the reference covariance carried over dt with the live filter's
 * transition, thesis seeds/002_cd7f1fdb7fc67471.txt eq 6.17, and its running means), with
 * MeanBudgetReference._propagate's mean of the live filter's position and orientation variance
 * traces where r->own is bound.  The scalars the reference keeps as attributes come in as
 * arguments and go out in r->st. */
void ct_scp_ref_propagate(const struct ct_sc *s, struct ct_scref *r, double dt, int64_t dt_us, double elapsed_us,
                          double mean_us, int settled, double settle_drop)
{
    const int n = CT_SC_CORE;
    double *P = r->P, *avg = r->avg, e, a, rr, du = (double)dt_us;
    const double *p = s->p;
    int i, g, k;
    ct_sc_build_F(s, r->F, n, r->q, dt);             /* ekf.core_transition */
    ct_congruence_sparse(n, r->F, P, r->T);
    for (i = 0; i < n; ++i)
        P[i * n + i] += r->q[i];
    elapsed_us += du;
    if (settle_drop <= 0.0) {
        e = elapsed_us - r->warmup_us;
        settled = e > 0.0;
    } else {
        if (settled)
            mean_us += du;
        e = mean_us;
    }
    a = e <= du ? 1.0 : du / (e < r->avg_us ? e : r->avg_us);
    if (a > 1.0)
        a = 1.0;
    rr = pow(p[0] * p[0] + p[1] * p[1] + p[2] * p[2], 0.5);
    rr = rr > 1e-3 ? rr : 1e-3;
    for (g = 0; g < 2; ++g) {
        double x = pow(rr, r->exp[g]);
        r->law[g] = r->law[g] < 0.0 ? x : r->law[g] + a * (x - r->law[g]);
    }
    for (k = 0; k < 3; ++k) {
        int pi = CT_POS + k, oi = CT_ORI + k;
        avg[k] += a * (P[pi * n + pi] - avg[k]);
        avg[3 + k] += a * (P[oi * n + oi] - avg[3 + k]);
    }
    if (r->own != NULL) {
        const double *L = s->P;
        int m = s->nx, b = CT_POS, o = CT_ORI;
        double x = L[b * m + b] + L[(b + 1) * m + b + 1] + L[(b + 2) * m + b + 2];
        r->own[0] += a * (x - r->own[0]);
        x = L[o * m + o] + L[(o + 1) * m + o + 1] + L[(o + 2) * m + o + 2];
        r->own[1] += a * (x - r->own[1]);
    }
    r->st[CT_REF_ELAPSED] = elapsed_us;
    r->st[CT_REF_MEAN] = mean_us;
    r->st[CT_REF_SETTLED] = settled ? 1.0 : 0.0;
    r->st[CT_REF_A] = a;
}

/* PoseCovUpdate.apply: P6 <- P6 - P6 H^T (H P6 H^T + R_v)^-1 H P6 with H = current Hu (Hu 3 x 6, hu 3),
 * symmetrised; 0 (P6 untouched) when the innovation covariance is not positive definite */
int ct_scp_pose_cov_update(struct ct_scp_cov *w, double *P6, const double *Hu, const double *hu, double current,
                           double var_amp, double rel_model, double current_sigma)
{
    double *A = w->A, *M = w->M, *G = w->G, *Si = w->Si, *T = w->T, *T2 = w->T2, s[9], hn2, r;
    int i, j, k;
    for (i = 0; i < 3; ++i)                          /* A = Hu P6, then A *= current */
        for (j = 0; j < 6; ++j) {
            double x = 0.0;
            for (k = 0; k < 6; ++k)
                x += Hu[i * 6 + k] * P6[k * 6 + j];
            A[i * 6 + j] = x;
        }
    for (i = 0; i < 18; ++i)
        A[i] = A[i] * current;
    for (i = 0; i < 3; ++i)                          /* M = A Hu^T, then M *= current */
        for (j = 0; j < 3; ++j) {
            double x = 0.0;
            for (k = 0; k < 6; ++k)
                x += A[i * 6 + k] * Hu[j * 6 + k];
            M[i * 3 + j] = x;
        }
    for (i = 0; i < 9; ++i)
        M[i] = M[i] * current;
    hn2 = hu[0] * hu[0] + hu[1] * hu[1] + hu[2] * hu[2];
    r = var_amp + (rel_model * rel_model * current * current + current_sigma * current_sigma) * hn2;
    s[0] = M[0] + r;                                 /* linalg.inv3_sym(M00 + r, M01, M02, M11 + r, M12, M22 + r) */
    s[3] = M[1];
    s[6] = M[2];
    s[4] = M[4] + r;
    s[7] = M[5];
    s[8] = M[8] + r;
    if (!ct_inv3(s, Si))
        return 0;
    for (i = 0; i < 3; ++i)                          /* G = Si A */
        for (j = 0; j < 6; ++j) {
            double x = 0.0;
            for (k = 0; k < 3; ++k)
                x += Si[i * 3 + k] * A[k * 6 + j];
            G[i * 6 + j] = x;
        }
    for (i = 0; i < 6; ++i)                          /* T = A^T G */
        for (j = 0; j < 6; ++j) {
            double x = 0.0;
            for (k = 0; k < 3; ++k)
                x += A[k * 6 + i] * G[k * 6 + j];
            T[i * 6 + j] = x;
        }
    for (i = 0; i < 36; ++i)
        P6[i] = P6[i] - T[i];
    memcpy(T2, P6, sizeof w->T2);                    /* symmetrise */
    for (i = 0; i < 6; ++i)
        for (j = 0; j < 6; ++j)
            P6[i * 6 + j] = T2[i * 6 + j] + T2[j * 6 + i];
    for (i = 0; i < 36; ++i)
        P6[i] = P6[i] * 0.5;
    return 1;
}

/* FixedCycleReference._pulse's measurement (accuracy.py): H (3 x nx) zero but for current times the
 * coil's per-ampere Jacobian Hu (3 x 6) in the position (columns pos..pos+2) and orientation (ori..ori+2)
 * blocks, R = r I3 with r = var_amp + (rel_model^2 current^2 + current_sigma^2) |hu|^2, y = 0; the
 * update itself is the shared KalmanUpdate's (ct_kalman_update) */
void ct_scp_ref_pulse_fill(int nx, double *H, double *R, double *y, const double *Hu, const double *hu,
                           double current, double var_amp, double rel_model, double current_sigma, int pos, int ori)
{
    double hn2, r;
    int i, j;
    for (i = 0; i < 3 * nx; ++i)
        H[i] = 0.0;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            H[i * nx + pos + j] = current * Hu[i * 6 + j];
            H[i * nx + ori + j] = current * Hu[i * 6 + 3 + j];
        }
    hn2 = hu[0] * hu[0] + hu[1] * hu[1] + hu[2] * hu[2];
    r = var_amp + (rel_model * rel_model * current * current + current_sigma * current_sigma) * hn2;
    for (i = 0; i < 9; ++i)
        R[i] = 0.0;
    for (i = 0; i < 3; ++i) {
        R[i * 3 + i] = r;
        y[i] = 0.0;
    }
}

/* coil_choice.NisMonitor.add: the window's NIS (nominal covariance) in the ring, its mean over the
 * values held, the chi-square test with hysteresis and the covariance-matching scale */
void ct_nis_add(struct ct_nis *m, double x)
{
    double *st = m->st, s, mean, a;
    int count = (int)st[CT_NIS_COUNT], head = (int)st[CT_NIS_HEAD], k, beyond, inc;
    if (!isfinite(x))
        x = 1e9;
    m->buf[head] = x;
    head = (head + 1) % m->window;
    if (count < m->window)
        count += 1;
    s = 0.0;
    for (k = 0; k < count; ++k)
        s += m->buf[k];
    mean = s / (double)count;
    st[CT_NIS_COUNT] = (double)count;
    st[CT_NIS_HEAD] = (double)head;
    st[CT_NIS_MEAN] = mean;
    st[CT_NIS_TOTAL] += 1.0;
    beyond = count >= m->min_count && mean > m->bound[count];
    inc = beyond && (st[CT_NIS_INCONSISTENT] != 0.0 || mean > m->min_mean);
    st[CT_NIS_INCONSISTENT] = inc ? 1.0 : 0.0;
    if (inc) {
        st[CT_NIS_FLAGGED] += 1.0;
        a = mean / m->dof;
        a = 1.0 > a ? 1.0 : a;                       /* min(max(a, 1.0), max_scale) */
        st[CT_NIS_R_SCALE] = m->max_scale < a ? m->max_scale : a;
    } else {
        st[CT_NIS_R_SCALE] = 1.0;
    }
}

/* coil_choice.NisMonitor.add_used: the exponential mean of NIS / dof with the covariance used */
void ct_nis_add_used(struct ct_nis *m, double x)
{
    double *st = m->st;
    x = x < m->excess_gate ? x : m->excess_gate;
    if (!(x >= 0.0))                                 /* NaN */
        x = m->excess_gate;
    if (x == HUGE_VAL)
        x = 10.0 * m->dof * m->max_scale;
    st[CT_NIS_EXCESS] += m->alpha * (x / m->dof - st[CT_NIS_EXCESS]);
}

/* coil_choice.saturation_current_limit: the largest current keeping every magnetometer axis in
 * range (HUGE_VAL: no axis constrains it; 0: the quiet field alone is beyond the margin) */
double ct_scp_saturation_current_limit(const double *hu, const double *quiet, double range_t, double margin,
                                       double gain)
{
    double lim = margin * range_t, best = HUGE_VAL;
    int k;
    for (k = 0; k < 3; ++k) {
        double a = gain * fabs(hu[k]);
        double room = lim - fabs(quiet[k]);
        if (room <= 0.0)
            return 0.0;
        if (a > 0.0) {
            double i = room / a;
            if (i < best)
                best = i;
        }
    }
    return best;
}

/* max(a, b) as Python's max: a unless b > a */
static double pymax2(double a, double b)
{
    return b > a ? b : a;
}

/* AdaptiveActuation._decide_limits for one sensor: every coil's limit (lim, n) lowered to the current
 * that keeps the magnetometer in range at the predicted position pp (3) with the position
 * uncertainty of P6 (6 x 6); h (n x 3): the per-ampere fields there; quiet (3) the latest quiet
 * field (have_quiet 0: none yet, the largest earth field assumed on every axis) */
void ct_scp_range_limits(int n, const double *h, const double *pp, const double *P6, const double *quiet,
                         int have_quiet, double saturation_sigmas, double range_t, double margin,
                         double earth_max_t, double *lim)
{
    static const double zero3[3] = {0.0, 0.0, 0.0};
    double r = sqrt(pp[0] * pp[0] + pp[1] * pp[1] + pp[2] * pp[2]);
    double sp = sqrt(pymax2(P6[0] + P6[7] + P6[14], 0.0));
    double gain = r > 0.0 ? pow(r / pymax2(r - saturation_sigmas * sp, 0.5 * r), 3.0) : 8.0;
    int c;
    for (c = 0; c < n; ++c) {
        double i;
        if (have_quiet)
            i = ct_scp_saturation_current_limit(h + 3 * c, quiet, range_t, margin, gain);
        else
            i = ct_scp_saturation_current_limit(h + 3 * c, zero3, range_t - earth_max_t / margin, margin, gain);
        if (i < lim[c])
            lim[c] = i;
    }
}

/* accuracy.FixedCycleReference.law_now: r^(2 e_g) / mean(r^(2 e_g)) */
static double law_now(const struct ct_scp_bounds *b, double r, int g)
{
    double m = b->law[g];
    if (!(m > 0.0))
        return 1.0;
    r = r > 1e-3 ? r : 1e-3;
    return pow(r, b->c[CT_BND_REF_EXP0 + g]) / m;
}

/* accuracy_budget.hold_factor */
static double hold_factor(const struct ct_scp_bounds *b, double own, double target)
{
    double f;
    if (!(target > 0.0))
        return 1.0;
    f = 2.0 - own / target;
    if (!(f > b->c[CT_BND_HOLD_MIN]))
        return b->c[CT_BND_HOLD_MIN];
    return f < b->c[CT_BND_HOLD_MAX] ? f : b->c[CT_BND_HOLD_MAX];
}

/* the reference's held_avg: its means (FixedCycleReference), or each group times its hold factor
 * (MeanBudgetReference.held_avg, writing factor and held) */
static const double *held_avg(struct ct_scp_bounds *b)
{
    double k2 = b->c[CT_BND_RATIO] * b->c[CT_BND_RATIO];
    int g, k;
    if (b->own == NULL)
        return b->avg;
    for (g = 0; g < 2; ++g) {
        int o = 3 * g;
        double t = b->avg[o] + b->avg[o + 1] + b->avg[o + 2];
        double f = hold_factor(b, b->own[g], k2 * t);
        b->factor[g] = f;
        for (k = o; k < o + 3; ++k)
            b->held[k] = b->avg[k] * f;
    }
    return b->held;
}

/* accuracy.fixed_cycle_bounds */
static void fixed_cycle_bounds(const double *avg6, double ratio, double min_ratio, double *mx, double *mn,
                               double law_pos, double law_ori)
{
    double k = 2.0 * ratio * ratio / (1.0 + min_ratio * min_ratio);
    int i;
    for (i = 0; i < 6; ++i) {
        double v = avg6[i] * (i < 3 ? law_pos : law_ori);
        double s = v > 0.0 ? pow(k * v, 0.5) : 0.0;
        mx[i] = s;
        mn[i] = min_ratio * s;
    }
}

/* AdaptiveActuation._stated_bounds */
static void stated_bounds(struct ct_scp_bounds *b)
{
    const double *c = b->c, d2r = 3.141592653589793 / 180.0;
    double sp = 1.0, so = 1.0;
    int k;
    if (c[CT_BND_RANGE_REF] > 0.0) {
        const double *pp = b->pp;
        double r = sqrt(pp[0] * pp[0] + pp[1] * pp[1] + pp[2] * pp[2]);
        double x = (1e-3 > r ? 1e-3 : r) / c[CT_BND_RANGE_REF];
        sp = pow(x, c[CT_BND_EXP_POS]);
        so = pow(x, c[CT_BND_EXP_ORI]);
    }
    for (k = 0; k < 3; ++k) {
        b->mx[k] = c[CT_BND_SMAX_POS] * sp;
        b->mn[k] = c[CT_BND_SMIN_POS] * sp;
        b->mx[3 + k] = c[CT_BND_SMAX_ORI] * d2r * so;
        b->mn[3 + k] = c[CT_BND_SMIN_ORI] * d2r * so;
    }
}

/* AdaptiveActuation._bounds: a sensor's decision bounds at its predicted position (ref_active: its
 * reference runs; warming: the fixed cycle's warm-up; excess: its NIS monitor's) */
void ct_scp_bounds(struct ct_scp_bounds *b, int ref_active, int warming, double excess)
{
    const double *c = b->c;
    double *mx = b->mx, *mn = b->mn;
    int k;
    if (ref_active && b->avg != NULL) {
        const double *pp = b->pp;
        double r = sqrt(pp[0] * pp[0] + pp[1] * pp[1] + pp[2] * pp[2]);
        const double *held = held_avg(b);
        fixed_cycle_bounds(held, c[CT_BND_RATIO], c[CT_BND_MIN_RATIO], mx, mn, law_now(b, r, 0), law_now(b, r, 1));
        if (warming) {
            static const int idx[6] = {CT_POS, CT_POS + 1, CT_POS + 2, CT_ORI, CT_ORI + 1, CT_ORI + 2};
            double k2 = c[CT_BND_CATCHUP] * pow(c[CT_BND_RATIO], 2.0);
            for (k = 0; k < 6; ++k) {
                int i = idx[k];
                double x = b->P[i * CT_SC_CORE + i] * k2;
                mx[k] = x > 0.0 ? sqrt(x) : 0.0;
                mn[k] = c[CT_BND_MIN_RATIO] * mx[k];
            }
        }
    } else {
        stated_bounds(b);
    }
    if (c[CT_BND_NIS] != 0.0) {
        double f;                                  /* accuracy.nis_bound_factor */
        if (!(excess > 1.0))
            f = 1.0;
        else
            f = excess < c[CT_BND_NIS_MAX] ? excess : c[CT_BND_NIS_MAX];
        f = sqrt(f);
        if (f != 1.0)
            for (k = 0; k < 6; ++k) {
                mx[k] = mx[k] / f;
                mn[k] = mn[k] / f;
            }
    }
}

/* PulseSchedule.command's frame: the payload little endian as struct.pack("<BHhQI") writes it */
int ct_pulse_cmd_frame(uint8_t *out, int seq, int src, int64_t coil, int64_t pulse_id, int64_t current_ma,
                       uint64_t start_us, int64_t duration_us)
{
    uint8_t raw[CT_PCMD_FRAME_RAW];
    uint8_t *pl = raw + 5;
    uint16_t ma;
    int i;
    if (coil < 0 || coil > 0xFF || pulse_id < 0 || pulse_id > 0xFFFF || current_ma < -32768 || current_ma > 32767 ||
        duration_us < 0 || duration_us > 0xFFFFFFFFLL)
        return -1;
    ma = (uint16_t)(int16_t)current_ma;
    pl[0] = (uint8_t)coil;
    pl[1] = (uint8_t)pulse_id;
    pl[2] = (uint8_t)(pulse_id >> 8);
    pl[3] = (uint8_t)ma;
    pl[4] = (uint8_t)(ma >> 8);
    for (i = 0; i < 8; ++i)
        pl[5 + i] = (uint8_t)(start_us >> (8 * i));
    for (i = 0; i < 4; ++i)
        pl[13 + i] = (uint8_t)((uint64_t)duration_us >> (8 * i));
    return ct_frame_seal(raw, CT_PCMD_PAYLOAD, seq, src, CT_PCMD_ID, CT_PCMD_CRC_EXTRA, out);
}

/* PulseBook.duty_ok: the on-time of [start, start + length) and of the coil's remembered pulses
 * that end inside the window [end - window_us, end), against the bound; the pairs that ended
 * before the window are skipped without reading their start, as in the reference */
int ct_scp_duty_ok(const int64_t *hist, int n_hist, int64_t start, int64_t length, int64_t window_us, double bound)
{
    int64_t end = start + length;
    int64_t w0 = end - window_us;
    int64_t on = length;
    int k;
    for (k = 0; k < n_hist; ++k) {
        int64_t e0 = hist[2 * k + 1];
        if (e0 > w0) {
            int64_t s0 = hist[2 * k];
            if (e0 > s0)
                on += (e0 < end ? e0 : end) - (s0 > w0 ? s0 : w0);
        }
    }
    return (double)on <= bound;
}

/* ActuationPolicy.set_bounds: var_max[k] = sigma_max6[k]^2 (1e-24 for a bound not above 0) */
void ct_scp_policy_set_bounds(double *var_max, const double *sigma_max6)
{
    int k;
    for (k = 0; k < 6; ++k) {
        double v = sigma_max6[k];
        var_max[k] = v > 0.0 ? v * v : 1e-24;
    }
}

/* ActuationPolicy.worst: max_k sqrt(P_kk / var_max_k) as sqrt(max_k P_kk / var_max_k) (the traces'
 * ratio with trace), the ratios' maximum started at 0 */
double ct_scp_policy_worst(const double *var_max, const double *P6, int trace)
{
    double u = 0.0, x;
    int g, k;
    if (trace) {
        for (g = 0; g < 6; g += 3) {
            x = (P6[g * 7] + P6[(g + 1) * 7] + P6[(g + 2) * 7]) / (var_max[g] + var_max[g + 1] + var_max[g + 2]);
            if (x > u)
                u = x;
        }
        return sqrt(u);
    }
    for (k = 0; k < 6; ++k) {
        x = P6[k * 7] / var_max[k];
        if (x > u)
            u = x;
    }
    return sqrt(u);
}

/* ActuationPolicy.due: a variance (a trace) not below its bound (NaN included), or the last update
 * max_interval_us old */
int ct_scp_policy_due(const double *var_max, const double *P6, int trace, int64_t now_us, int64_t last_update_us,
                      int64_t max_interval_us, int *reason)
{
    int g, k;
    if (trace) {
        for (g = 0; g < 6; g += 3)
            if (!(P6[g * 7] + P6[(g + 1) * 7] + P6[(g + 2) * 7] < var_max[g] + var_max[g + 1] + var_max[g + 2])) {
                *reason = 1;
                return 1;
            }
    } else {
        for (k = 0; k < 6; ++k)
            if (!(P6[k * 7] < var_max[k])) {
                *reason = 1;
                return 1;
            }
    }
    if (now_us - last_update_us >= max_interval_us) {
        *reason = 2;
        return 1;
    }
    *reason = 0;
    return 0;
}
