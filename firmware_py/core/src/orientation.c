/*
 * The orientation filter's covariance propagation: the compiled form of
 * coiltrack.firmware.estimate.orientation.OrientationFilter.propagate (thesis
 * seeds/002_cd7f1fdb7fc67471.txt eq 2.28 and the offset / disturbance rows, composed over the
 * steps since the last update):
 *
 *     theta_N = Gamma theta_0 - T_N (I + Gamma) / 2 b,  Gamma = R_N^T R_0,  d_N = c_d^N d_0
 *
 * with Q the sums of the per-step noises, then P <- A P A^T + Q (ct_covariance_predict) and
 * R_0 <- R_N.  The blocks are the reference's operations in the same order.
 */
#include "coiltrack_core.h"

void ct_orientation_propagate(const struct ct_ori *o, double dt_acc, double dt2_acc, double cd_acc,
                              double qd_acc)
{
    const double *R = o->R;
    double *Rc = o->Rc, *A = o->A, *Q = o->Q;
    int n = o->n, t0 = o->theta, b0 = o->bias, d0 = o->dist, i, j;
    double h = -0.5 * dt_acc;
    double qt = o->gyro_noise * o->gyro_noise * dt2_acc;
    double qb = o->gyro_bias_rw * o->gyro_bias_rw * dt_acc;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            double g = R[i] * Rc[j] + R[3 + i] * Rc[3 + j] + R[6 + i] * Rc[6 + j];
            A[(t0 + i) * n + t0 + j] = g;
            A[(t0 + i) * n + b0 + j] = h * g + (i == j ? h : 0.0);
        }
        A[(d0 + i) * n + d0 + i] = cd_acc;
    }
    for (i = 0; i < 3; ++i) {
        Q[(t0 + i) * n + t0 + i] = qt;
        Q[(b0 + i) * n + b0 + i] = qb;
        Q[(d0 + i) * n + d0 + i] = qd_acc;
    }
    ct_covariance_predict(n, A, o->P, Q, o->T);
    for (i = 0; i < 9; ++i)
        Rc[i] = R[i];
}
