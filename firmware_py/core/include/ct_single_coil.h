/*
 * The single-coil error-state EKF (Schepers & Veltink 2010, seeds/000_e46ec0e8bf7ea271.txt
 * sec. 2.1, eq 4) in C99: the compiled form of coiltrack.firmware.estimate.single_coil
 * (SchepersEKF: propagate, _step, _build_F, _fill_q, _orthonormalize, predict_pose, _inject,
 * pose_values with rotation.quat_from_elements),
 * estimate.clones (PoseClones.take, back, release, next_due, inject) and
 * estimate.single_coil_update (SingleCoilUpdate: _noise, _pass and run's passes around the shared
 * Kalman update, ct_kalman_update).  The Python is the reference: the same names (ct_sc_ prefix),
 * the same scalar operations in the same order; the products the reference hands to BLAS
 * (F P F^T, H P H^T, R dR) are summed here in increasing index order, so they agree to rounding.
 *
 * Every buffer is caller-owned (the numpy arrays the filter allocates at start-up), row-major.
 */
#ifndef CT_SINGLE_COIL_H
#define CT_SINGLE_COIL_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* the core block of the layout (estimate.layout.SCHEPERS_CORE: POS, VEL, ORI, ACC, GYR) */
#define CT_SC_CORE 15
/* the most clone slots a filter may have */
#define CT_SC_MAX_CLONES 8

/* one SchepersEKF's state and scratch */
struct ct_sc {
    int nx, nc;                        /* states; clone slots */
    double *p, *v, *R, *ba, *bg;       /* nominal state: 3, 3, 3x3, 3, 3 */
    double *f, *w;                     /* 3, 3: the interval's mean inputs, offsets removed */
    double *acc_prev, *gyr_prev;       /* 3, 3: the last raw samples */
    double *P, *F, *T, *q;             /* nx x nx covariance, transition, scratch; nx noise */
    double *Fc, *Pc, *Tc, *qc;         /* 15 x 15 (and 15) of the prediction ahead */
    double *TP, *TPT;                  /* 6 x nx, 6 x 6: scratch of a clone predicted backwards */
    double *E, *R2, *dR;               /* 3x3 scratch each */
    const double *fref;                /* 3: the specific force of the navigation frame (-g) */
    double *cl_p, *cl_R;               /* nc x 3, nc x 3 x 3: the clones' nominal poses */
    int64_t *cl_t;                     /* nc: their times, us */
    uint8_t *cl_due, *cl_taken;        /* nc: numpy bools */
    int cp[CT_SC_MAX_CLONES], co[CT_SC_MAX_CLONES];   /* the clones' first rows (C{k}P, C{k}O) */
    double qa, qpos, qg, qba, qbg;     /* squared densities: acc, pos, gyr noise; offset walks */
    int64_t steps;                     /* SchepersEKF._steps */
};

void ct_sc_fill_q(const struct ct_sc *s, double *q, double dt);
void ct_sc_build_F(const struct ct_sc *s, double *F, int n, double *q, double dt);
void ct_sc_step(struct ct_sc *s, double dt, int initialized);
void ct_sc_take_clone(struct ct_sc *s, int k, int initialized);
void ct_sc_release_clone(struct ct_sc *s, int k);
void ct_sc_back_clone(struct ct_sc *s, int k, double dt, const double *G, int initialized, double *TP, double *TPT);
int ct_sc_next_due(const struct ct_sc *s, int64_t t, int64_t until);
void ct_sc_propagate(struct ct_sc *s, int64_t t0, int64_t t_us, const double *acc, const double *gyr,
                     int initialized);
void ct_sc_predict_pose(struct ct_sc *s, double T, int n, double *P6, double *pp);
void ct_sc_inject(struct ct_sc *s, const double *dx);
void ct_sc_pose_values(const struct ct_sc *s, double *out);

/* one SingleCoilUpdate's buffers: the shared update's H (3 x nx), R (3 x 3), y (3), dx (nx) and
 * the passes' own */
struct ct_scu {
    int nx;
    double *H, *R, *y, *udx;           /* KalmanUpdate's */
    double *PHt, *S, *y_pred, *P0, *Pprev, *dx, *pi, *Ri, *Hdx, *dR;
    double *st;                        /* CT_SCU_NST scalars, below */
};
/* st[]: the pass's scalars, kept between the calls of one run */
enum { CT_SCU_HN2 = 0, CT_SCU_R2 = 1, CT_SCU_NIS_NOMINAL = 2, CT_SCU_NST = 3 };

/* one pass's measurement: the coil's per-ampere h (3) and H (3 x 6) and centre (3), the pulse */
struct ct_scm {
    const double *h, *Hu, *centre, *y, *var;
    double current, rel_model, r_scale;
    int gain;                 /* the coil gain's error row, -1: none (SingleCoilUpdate._pass) */
    double gain_current;      /* its column of H: gain_current h */
};
void ct_scu_predict(struct ct_scu *u, const struct ct_scm *m);
void ct_scu_noise(struct ct_scu *u, const double *P, const double *p, int cp, const struct ct_scm *m);
void ct_scu_begin(struct ct_scu *u, double *P, const double *p, const double *R, int cp, int co,
                  const struct ct_scm *m);
void ct_scu_pass(struct ct_scu *u, int it, double *P, int cp, int co, const struct ct_scm *m);
int ct_scu_after(struct ct_scu *u, int it, int flags, int iterations, double *P, const double *p,
                 const double *R, int cp, int co, const double *var);

#ifdef __cplusplus
}
#endif

#endif /* CT_SINGLE_COIL_H */
