/*
 * The adaptive single-coil policy's coil choice (actuate/coil_choice.py CoilChooser, Schepers &
 * Veltink 2010 sec. 2.1, eq 4); see ct_sc_choose.h.  Each function follows the Python method of
 * the same name operation by operation: the choice is a discrete decision, so its scores must be
 * the reference's to the bit.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* CoilChooser.set_bounds: the thresholds (6, m and rad) and the weights of J(P); a bound not
 * positive taken as 1e-12, a sigma_min outside (0, sigma_max] as sigma_max */
void ct_set_bounds(struct ct_chooser *ch, const double *sigma_max6, const double *sigma_min6)
{
    double *sm = ch->sigma_max;
    int g, k;
    for (k = 0; k < 6; ++k) {
        double smax = sigma_max6[k], smin = sigma_min6[k];
        if (!(smax > 0.0))
            smax = 1e-12;
        sm[k] = smax;
        ch->sigma_min[k] = (0.0 < smin && smin <= smax) ? smin : smax;
        ch->weight[k] = 1.0 / (smax * smax);
    }
    if (ch->trace)
        for (g = 0; g < 6; g += 3) {
            double w = 1.0 / (sm[g] * sm[g] + sm[g + 1] * sm[g + 1] + sm[g + 2] * sm[g + 2]);
            for (k = g; k < g + 3; ++k)
                ch->weight[k] = w;
        }
}

/* coil_choice.posterior_pose_variances: diag of P6 - I^2 A^T S^-1 A, S = I^2 M + R_v (eq 4), into
 * out (6); 0 (out = diag(P6)) when S is not positive definite */
int ct_posterior_pose_variances(const double *P6, const double *A, const double *M, double hnorm2, double current,
                                double var_amp, double rel_model, double *out, double current_sigma)
{
    double i2 = current * current, s[9], si[9], r;
    double s00, s01, s02, s11, s12, s22;
    int k;
    r = var_amp + (rel_model * rel_model * i2 + current_sigma * current_sigma) * hnorm2;
    s[0] = i2 * M[0] + r;                              /* linalg.inv3_sym(a00, a01, a02, a11, a12, a22) */
    s[3] = i2 * M[1];
    s[6] = i2 * M[2];
    s[4] = i2 * M[4] + r;
    s[7] = i2 * M[5];
    s[8] = i2 * M[8] + r;
    if (!ct_inv3(s, si)) {
        for (k = 0; k < 6; ++k)
            out[k] = P6[k * 6 + k];
        return 0;
    }
    s00 = si[0];
    s01 = si[1];
    s02 = si[2];
    s11 = si[4];
    s12 = si[5];
    s22 = si[8];
    for (k = 0; k < 6; ++k) {
        double a0 = A[k], a1 = A[6 + k], a2 = A[12 + k];
        double q = (a0 * (s00 * a0 + s01 * a1 + s02 * a2)
                    + a1 * (s01 * a0 + s11 * a1 + s12 * a2)
                    + a2 * (s02 * a0 + s12 * a1 + s22 * a2));
        out[k] = P6[k * 6 + k] - i2 * q;
    }
    return 1;
}

/* CoilChooser._products: A = Hu P6 (3 x 6) and M = A Hu^T (3 x 3) of coil c, each sum over k in
 * increasing order starting from its first term */
void ct_products(struct ct_chooser *ch, int c, const double *Hu, const double *P6)
{
    double *A = ch->A + 18 * c, *M = ch->M + 9 * c;
    int i, j;
    for (i = 0; i < 3; ++i) {
        const double *h = Hu + 6 * i;
        for (j = 0; j < 6; ++j)
            A[6 * i + j] = (h[0] * P6[j] + h[1] * P6[6 + j] + h[2] * P6[12 + j] + h[3] * P6[18 + j]
                            + h[4] * P6[24 + j] + h[5] * P6[30 + j]);
    }
    for (i = 0; i < 3; ++i) {
        const double *a = A + 6 * i;
        for (j = 0; j < 3; ++j) {
            const double *h = Hu + 6 * j;
            M[3 * i + j] = a[0] * h[0] + a[1] * h[1] + a[2] * h[2] + a[3] * h[3] + a[4] * h[4] + a[5] * h[5];
        }
    }
}

/* CoilChooser._gain_term: coil c's gain-error variance as a rank-one term of its eq-4 S,
 * M += gain_var[c] h h^T (h: coil c's 3 per-ampere field components), M[i][j] + (g h_i) h_j */
void ct_gain_term(struct ct_chooser *ch, int c, const double *hc)
{
    double *M = ch->M + 9 * c, g = ch->gain_var[c];
    int i;
    for (i = 0; i < 3; ++i) {
        double gh = g * hc[i];
        M[3 * i] = M[3 * i] + gh * hc[0];
        M[3 * i + 1] = M[3 * i + 1] + gh * hc[1];
        M[3 * i + 2] = M[3 * i + 2] + gh * hc[2];
    }
}

/* CoilChooser._ref_index: the largest candidate current <= limit, or -1 */
int ct_ref_index(const struct ct_chooser *ch, double limit)
{
    int j, k = -1;
    for (j = 0; j < ch->ncur; ++j) {
        if (ch->currents[j] <= limit * (1.0 + 1e-12))
            k = j;
        else
            break;
    }
    return k;
}

/* the target's group: [t, t + 3) with the trace bound, [t, t + 1) without */
static int group_end(const struct ct_chooser *ch)
{
    int t = (int)ch->st[CT_CH_TARGET];
    return ch->trace ? t + 3 : t + 1;
}

/* CoilChooser._pick_target: the variable (trace: the group, 0 or 3) furthest beyond its bound */
static void pick_target(struct ct_chooser *ch, const double *P6)
{
    const double *w = ch->weight;
    double best_u = -1.0;
    int g, k;
    if (ch->trace) {
        for (g = 0; g < 6; g += 3) {
            double u = (P6[g * 7] + P6[(g + 1) * 7] + P6[(g + 2) * 7]) * w[g];
            if (u > best_u) {
                best_u = u;
                ch->st[CT_CH_TARGET] = (double)g;
            }
        }
    } else {
        for (k = 0; k < 6; ++k) {
            double u = P6[k * 7] * w[k];
            if (u > best_u) {
                best_u = u;
                ch->st[CT_CH_TARGET] = (double)k;
            }
        }
    }
}

/* CoilChooser.unreached_goal */
static double unreached_goal(const struct ct_chooser *ch, double prior, double best)
{
    return best + (1.0 - ch->unreached_share) * (prior - best);
}

/* CoilChooser._prior: the target's prior variance (trace: summed over its group) */
static double prior(const struct ct_chooser *ch, const double *P6)
{
    double v = 0.0;
    int k, t1 = group_end(ch);
    for (k = (int)ch->st[CT_CH_TARGET]; k < t1; ++k)
        v += P6[k * 7];
    return v;
}

/* CoilChooser._group_after: the same over var_after */
static double group_after(const struct ct_chooser *ch)
{
    double v = 0.0;
    int k, t1 = group_end(ch);
    for (k = (int)ch->st[CT_CH_TARGET]; k < t1; ++k)
        v += ch->var_after[k];
    return v;
}

/* CoilChooser._goal: sigma_min^2 of the target (trace: summed over its group) */
static double goal_of(const struct ct_chooser *ch)
{
    double goal = 0.0;
    int k, t1 = group_end(ch);
    for (k = (int)ch->st[CT_CH_TARGET]; k < t1; ++k)
        goal += ch->sigma_min[k] * ch->sigma_min[k];
    return goal;
}

/* CoilChooser._smallest_current: the smallest rung up to kmax whose update of coil c brings the
 * target to goal (var_after its posterior), or -1 */
static int smallest_current(struct ct_chooser *ch, const double *P6, int c, double var_amp, int kmax, double goal)
{
    const double *A = ch->A + 18 * c, *M = ch->M + 9 * c;
    double hn2 = ch->hn2[c];
    int t = (int)ch->st[CT_CH_TARGET], t1 = group_end(ch), j, k;
    for (j = 0; j < kmax + 1; ++j) {
        double va = 0.0;
        ct_posterior_pose_variances(P6, A, M, hn2, ch->currents[j], var_amp, ch->rel_model, ch->var_after,
                                    ch->current_sigma);
        for (k = t; k < t1; ++k)
            va += ch->var_after[k];
        if (va <= goal)
            return j;
    }
    return -1;
}

/* CoilChooser._target_after: the target's posterior after coil c at i A (var_after the posterior) */
static double target_after(struct ct_chooser *ch, const double *P6, int c, double var_amp, double i)
{
    double va = 0.0;
    int k, t1;
    ct_posterior_pose_variances(P6, ch->A + 18 * c, ch->M + 9 * c, ch->hn2[c], i, var_amp, ch->rel_model,
                                ch->var_after, ch->current_sigma);
    t1 = group_end(ch);
    for (k = (int)ch->st[CT_CH_TARGET]; k < t1; ++k)
        va += ch->var_after[k];
    return va;
}

/* CoilChooser._refine: the smallest current (to step_a, rounded up) between rung j - 1 (0 A for
 * the first) and rung j reaching the goal, by bisection; rung j itself without a resolution */
static double refine(struct ct_chooser *ch, const double *P6, int c, double var_amp, int j, double goal)
{
    double hi = ch->currents[j], step = ch->step_a, lo, i;
    if (!(step > 0.0))
        return hi;
    lo = j > 0 ? ch->currents[j - 1] : 0.0;
    while (hi - lo > step) {
        double mid = 0.5 * (lo + hi);
        if (target_after(ch, P6, c, var_amp, mid) <= goal)
            hi = mid;
        else
            lo = mid;
    }
    i = ceil(hi / step - 1e-9) * step;
    if (i > ch->currents[j])
        i = ch->currents[j];
    target_after(ch, P6, c, var_amp, i);
    return i;
}

/* CoilChooser._strength: the smallest current bringing the target to sigma_min (the unreached
 * share's goal, or the largest allowed current, when none does) */
static int strength(struct ct_chooser *ch, const double *P6, int best_c, double var_amp, const double *i_limit)
{
    int kmax = ct_ref_index(ch, i_limit[best_c]), j;
    double goal = goal_of(ch), g2;
    j = smallest_current(ch, P6, best_c, var_amp, kmax, goal);
    if (j >= 0) {
        ch->st[CT_CH_CURRENT] = refine(ch, P6, best_c, var_amp, j, goal);
        ch->st[CT_CH_REACHED] = 1.0;
        return best_c;
    }
    if (ch->unreached_share > 0.0) {
        g2 = unreached_goal(ch, prior(ch, P6), group_after(ch));
        j = smallest_current(ch, P6, best_c, var_amp, kmax, g2);
        if (j >= 0) {
            ch->st[CT_CH_CURRENT] = refine(ch, P6, best_c, var_amp, j, g2);
            return best_c;
        }
    }
    ch->st[CT_CH_CURRENT] = ch->currents[kmax];
    ct_posterior_pose_variances(P6, ch->A + 18 * best_c, ch->M + 9 * best_c, ch->hn2[best_c], ch->st[CT_CH_CURRENT],
                                var_amp, ch->rel_model, ch->var_after, ch->current_sigma);
    return best_c;
}

/* CoilChooser.choose: the coil whose eq-4 update at its largest allowed current reduces
 * J(P) = sum_k P_kk w_k most, and its current (h: n x 3, H: n x 3 x 6 per ampere; i_limit: n) */
int ct_choose(struct ct_chooser *ch, const double *P6, const double *h, const double *H, double var_amp,
              const double *i_limit)
{
    const double *w = ch->weight;
    double j0 = 0.0, best_red = -HUGE_VAL, *var = ch->var;
    int best_c = -1, c, k, kk;
    pick_target(ch, P6);
    for (k = 0; k < 6; ++k)
        j0 += P6[k * 7] * w[k];
    for (c = 0; c < ch->n; ++c) {
        const double *hc = h + 3 * c;
        double i, j1, red;
        ct_products(ch, c, H + 18 * c, P6);
        if (ch->gain_var[c] > 0.0)
            ct_gain_term(ch, c, hc);
        ch->hn2[c] = hc[0] * hc[0] + hc[1] * hc[1] + hc[2] * hc[2];
        k = ct_ref_index(ch, i_limit[c]);
        if (k < 0) {
            ch->reduction[c] = -1.0;
            ch->i_ref[c] = 0.0;
            continue;
        }
        i = ch->currents[k];
        ch->i_ref[c] = i;
        ct_posterior_pose_variances(P6, ch->A + 18 * c, ch->M + 9 * c, ch->hn2[c], i, var_amp, ch->rel_model, var,
                                    ch->current_sigma);
        j1 = 0.0;
        for (kk = 0; kk < 6; ++kk)
            j1 += var[kk] * w[kk];
        red = j0 - j1;
        ch->reduction[c] = red;
        if (red > best_red) {
            best_red = red;
            best_c = c;
        }
    }
    ch->st[CT_CH_REACHED] = 0.0;
    ch->st[CT_CH_COIL] = (double)best_c;
    if (best_c < 0) {
        ch->st[CT_CH_CURRENT] = 0.0;
        for (k = 0; k < 6; ++k)
            ch->var_after[k] = P6[k * 7];
        return -1;
    }
    return strength(ch, P6, best_c, var_amp, i_limit);
}

/* CoilChooser.choose_length: choose at the longest length, then of every length's smallest
 * current reaching the goal the pair of least energy I^2 L (var_amps, lengths_us: nlen, shortest
 * first); the length's index in st[CT_CH_LENGTH] */
int ct_choose_length(struct ct_chooser *ch, const double *P6, const double *h, const double *H,
                     const double *var_amps, const double *lengths_us, int nlen, const double *i_limit)
{
    int last = nlen - 1, c, kmax, k, j;
    double goal, best_e, cur;
    c = ct_choose(ch, P6, h, H, var_amps[last], i_limit);
    ch->st[CT_CH_LENGTH] = (double)last;
    if (c < 0)
        return c;
    kmax = ct_ref_index(ch, i_limit[c]);
    if (ch->st[CT_CH_REACHED] != 0.0)
        goal = goal_of(ch);
    else if (ch->unreached_share > 0.0 && kmax >= 0)
        goal = unreached_goal(ch, prior(ch, P6), target_after(ch, P6, c, var_amps[last], ch->currents[kmax]));
    else
        return c;
    cur = ch->st[CT_CH_CURRENT];
    best_e = cur * cur * lengths_us[last];
    for (k = 0; k < last; ++k) {
        double i, e;
        j = smallest_current(ch, P6, c, var_amps[k], kmax, goal);
        if (j < 0)
            continue;
        i = refine(ch, P6, c, var_amps[k], j, goal);
        e = i * i * lengths_us[k];
        if (e < best_e) {
            best_e = e;
            ch->st[CT_CH_LENGTH] = (double)k;
            ch->st[CT_CH_CURRENT] = i;
        }
    }
    ct_posterior_pose_variances(P6, ch->A + 18 * c, ch->M + 9 * c, ch->hn2[c], ch->st[CT_CH_CURRENT],
                                var_amps[(int)ch->st[CT_CH_LENGTH]], ch->rel_model, ch->var_after,
                                ch->current_sigma);
    return c;
}
