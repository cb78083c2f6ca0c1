/*
 * The fusion filter's delayed magnetic update and its replay: the compiled form of
 * coiltrack.firmware.estimate.fusion_measurement (the measurement models' evaluate),
 * fusion_state.InsState.correct / copy_from and magnetic_inertial.FusionFilter.step (the replay
 * of the buffered IMU samples on the shadow state, with fusion_prediction.InertialPrediction's
 * history, and its propagate and set_dt through the forward path's ct_fus_step, fusimu.c).
 * Declarations and references: include/ct_fusion.h.
 *
 * The scalar steps are the reference's operations in the same order.  Where the reference calls
 * BLAS for a 3x3 product (Psi = Phi R_ms, Theta <- E Theta) the sum runs over k in increasing
 * order, equal to rounding.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* ------------------------------------------------------------ measurement */

/* linalg.rotvec_from_matrix: the rotation vector w, |w| <= pi, of the rotation r (row-major) */
void ct_fusion_rotvec_from_matrix(const double *r, double *w)
{
    double c = 0.5 * (r[0] + r[4] + r[8] - 1.0);
    double vx, vy, vz, s, angle, d, ax, ay, az, x, nrm;
    if (c > 1.0)
        c = 1.0;
    else if (c < -1.0)
        c = -1.0;
    vx = 0.5 * (r[7] - r[5]);
    vy = 0.5 * (r[2] - r[6]);
    vz = 0.5 * (r[3] - r[1]);
    s = sqrt(vx * vx + vy * vy + vz * vz);          /* sin(angle) */
    if (c > 0.0) {
        double f;
        angle = atan2(s, c);
        f = s < 1e-8 ? 1.0 + angle * angle / 6.0 : angle / s;
        w[0] = vx * f;
        w[1] = vy * f;
        w[2] = vz * f;
        return;
    }
    /* angle in [pi/2, pi]: axis from the symmetric part (Python's max(x, 0.0) keeps a NaN) */
    angle = atan2(s, c);
    d = 1.0 - c;
    x = (r[0] - c) / d;
    ax = sqrt(0.0 > x ? 0.0 : x);
    x = (r[4] - c) / d;
    ay = sqrt(0.0 > x ? 0.0 : x);
    x = (r[8] - c) / d;
    az = sqrt(0.0 > x ? 0.0 : x);
    if (ax >= ay && ax >= az) {
        ay = copysign(ay, r[1] + r[3]);
        az = copysign(az, r[2] + r[6]);
        if (vx < 0.0) {
            ax = -ax;
            ay = -ay;
            az = -az;
        }
    } else if (ay >= az) {
        ax = copysign(ax, r[1] + r[3]);
        az = copysign(az, r[5] + r[7]);
        if (vy < 0.0) {
            ax = -ax;
            ay = -ay;
            az = -az;
        }
    } else {
        ax = copysign(ax, r[2] + r[6]);
        ay = copysign(ay, r[5] + r[7]);
        if (vz < 0.0) {
            ax = -ax;
            ay = -ay;
            az = -az;
        }
    }
    nrm = sqrt(ax * ax + ay * ay + az * az);
    w[0] = ax * angle / nrm;
    w[1] = ay * angle / nrm;
    w[2] = az * angle / nrm;
}

/* fusion_measurement._position_and_white: y[zp..] = Phi q - p; Psi = Phi R_ms; the white blocks
 * Phi C_pp Phi^T, Psi C_tt Psi^T, Phi C_pt Psi^T (times mag_var_scale) into P */
static void position_and_white(const struct ct_fusmeas *m, const double *Phi, const double *q,
                               const double *R_ms, const double *C, const double *p, double *P, double *y,
                               double *Psi)
{
    const int n = m->n, zp = m->zp, q0 = m->q0, s0 = m->s0, cp = m->cp, co = m->co;
    const double s = m->mag_var_scale;
    int i, j, a, b;
    for (i = 0; i < 3; ++i)
        y[zp + i] = Phi[3 * i] * q[0] + Phi[3 * i + 1] * q[1] + Phi[3 * i + 2] * q[2] - p[i];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            Psi[3 * i + j] = Phi[3 * i] * R_ms[j] + Phi[3 * i + 1] * R_ms[3 + j] + Phi[3 * i + 2] * R_ms[6 + j];
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            double cpp = 0.0, cpt = 0.0, ctt = 0.0;
            for (a = 0; a < 3; ++a) {
                double fa = Phi[3 * i + a];
                double pa = Psi[3 * i + a];
                for (b = 0; b < 3; ++b) {
                    cpp += fa * C[6 * (cp + a) + cp + b] * Phi[3 * j + b];
                    cpt += fa * C[6 * (cp + a) + co + b] * Psi[3 * j + b];
                    ctt += pa * C[6 * (co + a) + co + b] * Psi[3 * j + b];
                }
            }
            P[(q0 + i) * n + q0 + j] = cpp * s;
            P[(q0 + i) * n + s0 + j] = cpt * s;
            P[(s0 + j) * n + q0 + i] = cpt * s;
            P[(s0 + i) * n + s0 + j] = ctt * s;
        }
}

/* fusion_measurement._log_diff: y[row..] = log(Z Theta^T) */
static void log_diff(const double *Z, const double *Th, double *y, int row)
{
    double r[9];
    int i, j;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            r[3 * i + j] = Z[3 * i] * Th[3 * j] + Z[3 * i + 1] * Th[3 * j + 1] + Z[3 * i + 2] * Th[3 * j + 2];
    ct_fusion_rotvec_from_matrix(r, y + row);
}

/* pose.covariance.RotationMargin.realized_into: the rest of the second-order margin for an
 * orientation error known to be |theta|^2 = t2 (at most CT_MARGIN_MAX_ORI_VAR) where it exceeds
 * the expected tr(C_tt), turned by Phi into the filter's frame, times mag_var_scale, added to
 * P[q0.., q0..]; nothing when t2 is within the expected or C_tt is not positive definite. */
static void rotation_margin_realized(const struct ct_fusmeas *m, const double *C, double t2, const double *Phi,
                                     double *P)
{
    const int n = m->n, q0 = m->q0, cp = m->cp, co = m->co;
    const double *Ct = C + 6 * co + co;          /* C_tt's first element */
    double s[9], inv[9], d[9], tr, f, g, i00, i01, i02, i11, i12, i22;
    int i, j, a, b;
    tr = Ct[0] + Ct[7] + Ct[14];
    t2 = t2 < CT_MARGIN_MAX_ORI_VAR ? t2 : CT_MARGIN_MAX_ORI_VAR;
    if (!(tr > 0.0 && t2 > tr && isfinite(tr)))
        return;
    s[0] = Ct[0]; s[3] = s[1] = Ct[1]; s[6] = s[2] = Ct[2];
    s[4] = Ct[7]; s[7] = s[5] = Ct[8]; s[8] = Ct[14];
    if (!ct_inv3(s, inv))
        return;
    i00 = inv[0]; i01 = inv[1]; i02 = inv[2]; i11 = inv[4]; i12 = inv[5]; i22 = inv[8];
    f = 0.25 * (t2 - tr);
    g = 2.0 / tr;
    for (i = 0; i < 3; ++i) {
        const double *ci = C + 6 * (cp + i) + co;
        const double c0 = ci[0], c1 = ci[1], c2 = ci[2];
        const double k0 = c0 * i00 + c1 * i01 + c2 * i02;
        const double k1 = c0 * i01 + c1 * i11 + c2 * i12;
        const double k2 = c0 * i02 + c1 * i12 + c2 * i22;
        for (j = i; j < 3; ++j) {
            const double *cj = C + 6 * (cp + j) + co;
            const double e0 = cj[0], e1 = cj[1], e2 = cj[2];
            const double v = f * (k0 * e0 + k1 * e1 + k2 * e2 + g * (c0 * e0 + c1 * e1 + c2 * e2));
            d[3 * i + j] = v;
            d[3 * j + i] = v;
        }
    }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            double acc = 0.0;
            for (a = 0; a < 3; ++a)
                for (b = 0; b < 3; ++b)
                    acc += Phi[3 * i + a] * d[3 * a + b] * Phi[3 * j + b];
            P[(q0 + i) * n + q0 + j] += acc * m->mag_var_scale;
        }
}

void ct_fusion_evaluate(const struct ct_fusmeas *m, int xi_model, const double *Phi, const double *Xi,
                        const double *XiP, const double *q, const double *R_ms, const double *C,
                        const double *p, const double *Th, double *P, double *y, double *Psi)
{
    const int n = m->n;
    int i, j;
    position_and_white(m, Phi, q, R_ms, C, p, P, y, Psi);
    if (!xi_model) {                         /* MagneticOrientation.evaluate */
        log_diff(Psi, Th, y, m->zpsi);
        return;
    }
    /* InertialMagneticOrientation.evaluate */
    if (m->zpsi >= 0) {
        const int z = m->zpsi;
        log_diff(Psi, Th, y, z);
        /* the position's margin for the orientation error this solution has (pose.covariance) */
        rotation_margin_realized(m, C, y[z] * y[z] + y[z + 1] * y[z + 1] + y[z + 2] * y[z + 2], Phi, P);
    }
    log_diff(Xi, Th, y, m->zxi);
    for (i = 0; i < 3; ++i) {
        double *row = P + (m->x0 + i) * n + m->x0;
        for (j = 0; j < 3; ++j)
            row[j] = XiP[3 * i + j] * m->xi_var_scale;
        row[i] += i == 2 ? m->xi_heading_floor2 : m->xi_floor2;
    }
    if (m->zpsi < 0) {
        /* the magnetic orientation is not used: keep its white block inert */
        const int q0 = m->q0, s0 = m->s0;
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j) {
                P[(s0 + i) * n + s0 + j] = i == j ? m->psi_var : 0.0;
                P[(q0 + i) * n + s0 + j] = 0.0;
                P[(s0 + j) * n + q0 + i] = 0.0;
            }
    }
}

/* ------------------------------------------------------------ the state */

void ct_fusion_correct(const struct ct_fusstate *s, const double *dx)
{
    double E[9], T[9];
    int i, j;
    for (i = 0; i < 3; ++i) {
        s->p[i] += dx[CT_POS + i];
        s->v[i] += dx[CT_VEL + i];
        s->ba[i] += dx[CT_ACC + i];
        s->bg[i] += dx[CT_GYR + i];
    }
    ct_exp_rotvec(dx[CT_ORI], dx[CT_ORI + 1], dx[CT_ORI + 2], E);
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            T[3 * i + j] = E[3 * i] * s->Th[j] + E[3 * i + 1] * s->Th[3 + j] + E[3 * i + 2] * s->Th[6 + j];
    memcpy(s->Th, T, sizeof T);
}

void ct_fusion_copy(const struct ct_fusstate *dst, const struct ct_fusstate *src)
{
    memcpy(dst->p, src->p, 3 * sizeof(double));
    memcpy(dst->v, src->v, 3 * sizeof(double));
    memcpy(dst->Th, src->Th, 9 * sizeof(double));
    memcpy(dst->ba, src->ba, 3 * sizeof(double));
    memcpy(dst->bg, src->bg, 3 * sizeof(double));
    memcpy(dst->P, src->P, (size_t)src->n * (size_t)src->n * sizeof(double));
}

/* ------------------------------------------------------------ the replay */

/* ekf.symmetrize in place: P = (P + P^T) / 2 */
static void symmetrize(double *P, int n)
{
    int i, j;
    for (i = 0; i < n; ++i) {
        P[i * n + i] = (P[i * n + i] + P[i * n + i]) * 0.5;
        for (j = i + 1; j < n; ++j) {
            double a = P[i * n + j], b = P[j * n + i];
            P[i * n + j] = (a + b) * 0.5;
            P[j * n + i] = (b + a) * 0.5;
        }
    }
}

/* InertialPrediction.propagate and step_compiled of the shadow over [t0, t1] with the IMU samples
 * of slots k - 1 and k (ct_fus_step, fusimu.c: the forward path's step), then
 * CovariancePredict.after_predict */
static void replay_propagate(const struct ct_replay *r, int64_t k, int64_t t0, int64_t t1, int64_t *io, double *fo)
{
    ct_fus_step(&r->ins, r->Qd, r->dtk, fo, r->imu_t, r->imu_d, r->imu_cap, k, io[CT_RIO_IMU_COUNT], t0, t1);
    io[CT_RIO_PRED_COUNT] += 1;
    if (io[CT_RIO_PRED_COUNT] % r->symmetrize_every == 0)
        symmetrize(r->ins.P, r->ins.n);
    io[CT_RIO_STEPS] += 1;
}

/* InertialPrediction.history: push the shadow's pose at t in the source frame (to_source, Phi of
 * IMU slot k) onto the shadow history; *head, *count: the ring's */
static void replay_history(const struct ct_replay *r, int64_t k, int64_t t, int64_t *head, int64_t *count,
                           int64_t *io)
{
    const int64_t h = *head;
    const double *p = r->ins.p, *Th = r->ins.Th;
    double *hd = r->hist_d + h * CT_HIST_WIDTH;
    int i, j;
    r->hist_t[h] = t;
    *head = h + 1 == r->hist_cap ? 0 : h + 1;
    if (*count < r->hist_cap)
        *count += 1;
    io[CT_RIO_HIST_PUSHED] += 1;
    if (r->fixed) {
        hd[CT_HIST_P] = p[0];
        hd[CT_HIST_P + 1] = p[1];
        hd[CT_HIST_P + 2] = p[2];
        for (i = 0; i < 9; ++i)
            hd[CT_HIST_R + i] = Th[i];
        return;
    }
    {
        const double *F = r->imu_d + k * CT_IMU_WIDTH + CT_IMU_PHI;
        for (i = 0; i < 3; ++i) {
            double f0 = F[i], f1 = F[3 + i], f2 = F[6 + i];       /* column i of Phi */
            hd[CT_HIST_P + i] = f0 * p[0] + f1 * p[1] + f2 * p[2];
            for (j = 0; j < 3; ++j)
                hd[CT_HIST_R + 3 * i + j] = f0 * Th[j] + f1 * Th[3 + j] + f2 * Th[6 + j];
        }
    }
}

int ct_fusion_replay(const struct ct_replay *r, int64_t *io, double *fo, int budget)
{
    const int64_t cap = r->imu_cap, first = io[CT_RIO_IMU_FIRST], count = io[CT_RIO_IMU_COUNT];
    const int pending = io[CT_RIO_SNAP_PENDING] != 0;
    const int64_t ts = io[CT_RIO_SNAP_T];
    int64_t t = io[CT_RIO_T];
    int64_t hcount = io[CT_RIO_HIST_COUNT];
    int64_t head = io[CT_RIO_HIST_FIRST] + hcount;
    int64_t units = io[CT_RIO_UNITS];
    int rc;
    if (head >= r->hist_cap)
        head -= r->hist_cap;
    io[CT_RIO_STEPS] = 0;
    io[CT_RIO_HIST_PUSHED] = 0;
    if (io[CT_RIO_SPLIT] >= 0) {
        /* the rest of the step split at the snapshot (taken by the caller at t) */
        const int64_t k = io[CT_RIO_SPLIT], tk = r->imu_t[k];
        io[CT_RIO_SPLIT] = -1;
        if (tk > t) {
            replay_propagate(r, k, t, tk, io, fo);
            units += 1;
        }
        t = tk;
        replay_history(r, k, t, &head, &hcount, io);
    }
    for (;;) {
        const int64_t i = ct_times_index_at_or_after(r->imu_t, cap, first + count, count, t + 1);
        int64_t k, tk, t0;
        if (i >= count) {
            rc = CT_REPLAY_CAUGHT_UP;
            break;
        }
        if (units >= budget) {
            rc = CT_REPLAY_BUDGET;
            break;
        }
        if (i == 0) {
            rc = CT_REPLAY_LOST;
            break;
        }
        k = first + i;
        if (k >= cap)
            k -= cap;
        tk = r->imu_t[k];
        t0 = t;
        if (pending && t0 < ts && ts <= tk) {
            /* FusionFilter._advance: the step split at the snapshot time */
            if (ts > t0) {
                replay_propagate(r, k, t0, ts, io, fo);
                t = ts;
                replay_history(r, k, t, &head, &hcount, io);
                units += 1;
            }
            io[CT_RIO_SPLIT] = k;
            rc = CT_REPLAY_SNAPSHOT;
            break;
        }
        replay_propagate(r, k, t0, tk, io, fo);
        units += 1;
        t = tk;
        replay_history(r, k, t, &head, &hcount, io);
    }
    io[CT_RIO_T] = t;
    io[CT_RIO_UNITS] = units;
    return rc;
}

/* ------------------------------------------------------------ the burst's side */

/* Snapshot.take_aux: FixedSource / MovingSource.phi_into, then (Xi initialised) the copies of R
 * and bias and OrientationFilter.theta_covariance_global's sum in its order */
void ct_fusion_snap_aux(int fixed, const double *imu_row, int xi, const double *R, const double *P, int np, int t0,
                        const double *bias, double *Phi, double *Xi, double *XiP, double *XiB)
{
    int i, j, k, m;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            Phi[3 * i + j] = fixed ? (i == j ? 1.0 : 0.0) : imu_row[CT_IMU_PHI + 3 * i + j];
    if (!xi)
        return;
    memcpy(Xi, R, 9 * sizeof(double));
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            double acc = 0.0;
            for (k = 0; k < 3; ++k) {
                const double rik = R[3 * i + k];
                for (m = 0; m < 3; ++m)
                    acc += rik * P[(t0 + k) * np + t0 + m] * R[3 * j + m];
            }
            XiP[3 * i + j] = acc;
        }
    memcpy(XiB, bias, 3 * sizeof(double));
}

/* PoseHistory.pose_at: ring.Ring.index_at_or_after, the two rows about t_us, their blend */
int ct_fusion_pose_at(const int64_t *ht, const double *hd, int64_t cap, int64_t head, int64_t count, int64_t t_us,
                      double *out_p, double *out_R)
{
    int64_t i, prev, k, t0, tk;
    double a, b;
    int c, r, j;
    if (count < 2)
        return 0;
    i = ct_times_index_at_or_after(ht, cap, head, count, t_us);
    if (i >= count)
        return 0;
    if (i == 0) {
        if (ht[ct_times_slot(cap, head, count, 0)] != t_us)
            return 0;
        i = 1;
    }
    prev = ct_times_slot(cap, head, count, i - 1);
    k = ct_times_slot(cap, head, count, i);
    t0 = ht[prev];
    tk = ht[k];
    a = tk > t0 ? (double)(t_us - t0) / (double)(tk - t0) : 1.0;
    b = 1.0 - a;
    for (c = 0; c < 3; ++c)
        out_p[c] = b * hd[prev * CT_HIST_WIDTH + CT_HIST_P + c] + a * hd[k * CT_HIST_WIDTH + CT_HIST_P + c];
    for (r = 0; r < 3; ++r)
        for (j = 0; j < 3; ++j) {
            c = CT_HIST_R + 3 * r + j;
            out_R[3 * r + j] = b * hd[prev * CT_HIST_WIDTH + c] + a * hd[k * CT_HIST_WIDTH + c];
        }
    return 1;
}

/* SensorInertial.motion_cov (InsState.velocity_sigma and speed_squared inline, their operations) */
void ct_fusion_motion_cov(const double *C, double *out, const double *p, int compensated, int initialized,
                          double tr2, const double *P, int n, const double *v, const double *w)
{
    double ap, ao;
    int i;
    memcpy(out, C, 36 * sizeof(double));
    if (compensated) {
        const int v0 = CT_VEL;
        double s = P[v0 * n + v0] + P[(v0 + 1) * n + v0 + 1] + P[(v0 + 2) * n + v0 + 2];
        double sv = sqrt((s > 0.0 ? s : (s == s ? 0.0 : s)) / 3.0);
        ap = sv * sv * tr2;
        ao = 0.0;
    } else {
        ao = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * tr2;
        ap = initialized ? (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * tr2 : 0.0;
        ap += (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) * ao;
    }
    for (i = 0; i < 3; ++i) {
        out[i * 6 + i] += ap;
        out[(3 + i) * 6 + 3 + i] += ao;
    }
}

/* SensorInertial.compensate_begin (np.copyto, FilterView.velocity_sigma, PoseHistory.pose_at) */
int ct_fusion_comp_begin(const double *S, double *S_comp, int n, int initialized, const double *P, int n_st,
                         double max_sigma, const int64_t *ht, const double *hd, int64_t cap, int64_t head,
                         int64_t count, int64_t t_ref, double *p_ref, double *R_ref)
{
    const int v0 = CT_VEL;
    double s, sv;
    memcpy(S_comp, S, (size_t)(3 * n) * sizeof(double));
    if (!initialized)
        return 0;
    s = P[v0 * n_st + v0] + P[(v0 + 1) * n_st + v0 + 1] + P[(v0 + 2) * n_st + v0 + 2];
    sv = sqrt((s > 0.0 ? s : (s == s ? 0.0 : s)) / 3.0);
    if (sv > max_sigma)
        return 0;
    return ct_fusion_pose_at(ht, hd, cap, head, count, t_ref, p_ref, R_ref);
}

/* SensorInertial.compensate_step's loop body after the prediction of pulse j */
void ct_fusion_comp_add(double *S_comp, const double *h_ref, const double *h_j, int n, int j)
{
    int i;
    for (i = 0; i < 3; ++i)
        S_comp[i * n + j] = S_comp[i * n + j] + h_ref[i * n + j] - h_j[i * n + j];
}

/* PoseHistory.rewind_shadow (drop) / commit: Ring.copy_from (the whole arrays, head and count), then
 * Ring.drop_newer_than (index_at_or_after(t_us + 1), the head moved back over the newer entries) */
/* Where dst lies just above src modulo 4 KiB (the two rings' arrays are allocated one after the
 * other, e.g. 98320 bytes apart), a forward copy's every load follows a store with the same low 12
 * address bits: the processor takes them for dependent (4K aliasing) and memcpy of a 98 KB history
 * took 36 us instead of 3.  Copied from the end then, no load follows a store it aliases; the
 * same values either way. */
static int aliased_forward(const void *dst, const void *src)
{
    const uintptr_t gap = ((uintptr_t)dst - (uintptr_t)src) & 4095u;
    return gap != 0 && gap <= 512;
}

/* dst = src, n doubles (not overlapping) */
static void copy_doubles(double *dst, const double *src, int64_t n)
{
    int64_t i;
    if (!aliased_forward(dst, src)) {
        memcpy(dst, src, (size_t)n * sizeof(double));
        return;
    }
    for (i = n - 1; i >= 0; --i)
        dst[i] = src[i];
}

/* dst = src, n int64 (not overlapping) */
static void copy_int64(int64_t *dst, const int64_t *src, int64_t n)
{
    int64_t i;
    if (!aliased_forward(dst, src)) {
        memcpy(dst, src, (size_t)n * sizeof(int64_t));
        return;
    }
    for (i = n - 1; i >= 0; --i)
        dst[i] = src[i];
}

void ct_fusion_hist_copy(int64_t *dt, double *dd, int64_t *dhc, const int64_t *st, const double *sd, const int64_t *shc,
                         int64_t cap, int drop, int64_t t_us)
{
    int64_t lo, h;
    copy_int64(dt, st, cap);
    copy_doubles(dd, sd, cap * CT_HIST_WIDTH);
    dhc[0] = shc[0];
    dhc[1] = shc[1];
    if (!drop)
        return;
    lo = ct_times_index_at_or_after(dt, cap, dhc[0], dhc[1], t_us + 1);
    h = dhc[0] - (dhc[1] - lo);
    dhc[0] = h < 0 ? h + cap : h;
    dhc[1] = lo;
}

/* FusionFilter._restore (prepare_magnetic_update): InsState.copy_from of the snapshot's state,
 * PoseHistory.rewind_shadow, the measurement model's evaluate; the same three kernels in order */
void ct_fusion_prepare(const struct ct_fusprep *f, int64_t t_ref, const double *q, const double *R_ms,
                       const double *C)
{
    const struct ct_fusstate *sh = f->shadow;
    ct_fusion_copy(sh, f->snap);
    if (f->hist_mark)
        ct_hist_sync(f->live_t, f->live_d, f->live_hc, f->shadow_t, f->shadow_d, f->shadow_hc, f->hist_cap,
                     f->hist_mark, 1, t_ref);
    else
        ct_fusion_hist_copy(f->shadow_t, f->shadow_d, f->shadow_hc, f->live_t, f->live_d, f->live_hc, f->hist_cap,
                            1, t_ref);
    ct_fusion_evaluate(f->m, f->xi_model, f->Phi, f->Xi, f->XiP, q, R_ms, C, sh->p, sh->Th, sh->P, f->y, f->Psi);
}

/* FusionFilter._update_shadow: KalmanUpdate.update of the shadow's P (with its symmetrisation when
 * sym), then InsState.correct, as the reference calls them */
int ct_fusion_update(const struct ct_kalman *u, const struct ct_fusstate *s, double gate, int sym, double *nis)
{
    int flags = ct_kalman_update(u, s->P, gate, nis);
    if (flags != CT_EKF_OK)
        return flags;
    if (sym)
        symmetrize(s->P, s->n);
    ct_fusion_correct(s, u->dx);
    return flags;
}
