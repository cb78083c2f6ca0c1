/*
 * The adaptive single-coil policy's coil choice (Schepers & Veltink 2010,
 * seeds/000_e46ec0e8bf7ea271.txt sec. 2.1, eq 4 with the single-coil model of eqs 5-11) in C99:
 * the compiled form of coiltrack.firmware.actuate.coil_choice (posterior_pose_variances,
 * CoilChooser.set_bounds, CoilChooser.choose with _pick_target, _ref_index, _strength, _goal, _prior, _group_after,
 * unreached_goal, _smallest_current, _target_after, _refine, _products and _gain_term, and choose_length).
 * The Python is the reference: the same names (ct_ prefix), the same scalar operations in the
 * same order, so the scores compared, the coil, the current and the length are bit for bit the
 * reference's (the products Hu P6 and A Hu^T summed in increasing index order in both; the
 * 3 x 3 inverse is linalg.inv3_sym's, ct_inv3).  Every buffer is caller-owned, row-major.
 */
#ifndef CT_SC_CHOOSE_H
#define CT_SC_CHOOSE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* st[]: the choice (CoilChooser's coil, current, length, target, reached; the integers and the
 * flag held as doubles), kept between calls as the reference's attributes are */
enum { CT_CH_COIL, CT_CH_CURRENT, CT_CH_LENGTH, CT_CH_TARGET, CT_CH_REACHED, CT_CH_NST };

/* one CoilChooser: its arrays (the reference's own, bound) and constants */
struct ct_chooser {
    int n, ncur, trace;
    const double *currents;            /* ncur, ascending */
    double *sigma_max, *sigma_min;     /* 6, 6: the bounds (ct_set_bounds writes them) */
    double *weight;                    /* 6: 1 / sigma_max^2 (trace: of the group's sum) */
    double *A, *M, *hn2;               /* n x 3 x 6, n x 3 x 3, n */
    double *reduction, *i_ref;         /* n, n */
    double *var, *var_after;           /* 6 (scratch), 6 */
    double *st;                        /* CT_CH_NST */
    const double *gain_var;            /* n: each coil's gain-error variance (0: no term) */
    double rel_model, current_sigma, step_a, unreached_share;
};

void ct_set_bounds(struct ct_chooser *ch, const double *sigma_max6, const double *sigma_min6);
int ct_posterior_pose_variances(const double *P6, const double *A, const double *M, double hnorm2, double current,
                                double var_amp, double rel_model, double *out, double current_sigma);
void ct_products(struct ct_chooser *ch, int c, const double *Hu, const double *P6);
void ct_gain_term(struct ct_chooser *ch, int c, const double *hc);
int ct_ref_index(const struct ct_chooser *ch, double limit);
int ct_choose(struct ct_chooser *ch, const double *P6, const double *h, const double *H, double var_amp,
              const double *i_limit);
int ct_choose_length(struct ct_chooser *ch, const double *P6, const double *h, const double *H,
                     const double *var_amps, const double *lengths_us, int nlen, const double *i_limit);

#ifdef __cplusplus
}
#endif

#endif /* CT_SC_CHOOSE_H */
