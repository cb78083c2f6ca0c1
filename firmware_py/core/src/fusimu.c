/*
 * The per-IMU-sample path of the fused trackers, compiled:
 *
 * - ct_fus_step / ct_fus_propagate: coiltrack.firmware.estimate.fusion_prediction
 *   .InertialPrediction.propagate (the inputs at t0, t1 interpolated between IMU ring rows k - 1 and
 *   k) with step_compiled and set_dt (ct_fus_set_dt), the one step the replay (fusion.c) runs too: thesis seeds/002_cd7f1fdb7fc67471.txt eqs 6.1-6.4, 6.8 (strapdown, ct_ins_propagate),
 *   6.10, 6.13-6.14 (the step's static blocks of A and its Q, sec 6.2.4), 6.17, 6.5;
 * - ct_fus_to_source: fusion_state.MovingSource.to_source / FixedSource.to_source (eq 6.7:
 *   p_M = Phi^T p, R_MS = Phi^T Theta);
 * - ct_fus_output: fusion_output.PoseOutput.queue with _quat_into (rotation.quat_from_elements,
 *   Shepperd's method) and MovingSource / FixedSource.position_var;
 * - ct_ori_predict: estimate.orientation.OrientationFilter.predict (eq 2.27 strapdown, eq 2.5
 *   acceleration and eq 2.7 disturbance decay, the sums the covariance propagation composes).
 *
 * - ct_quiet_sample: track.burst_fusion.quiet_sample with measure.pulse.SampleRing.nearest_slot and
 *   PulseGate.quiet (the compass sample of the ch. 2 filter: thesis seeds/002_cd7f1fdb7fc67471.txt
 *   ch. 2 needs the earth field alone, outside the coil pulses).
 *
 * Each follows its Python reference operation by operation, in the same order.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* InertialPrediction.set_dt: the parts of A (ins->A) and of Q's diagonal that depend on the step
 * alone, and the step's scalars ws[CT_FS_*]; dtk: InertialPrediction._dtk (tau_a, tau_g, the
 * velocity's noise density, gyro_noise, the offsets' random walks).  The orientation's noise
 * (k[3] * dt) ** 2 is the correctly rounded square go * go (what a compiler makes of
 * pow(go, 2.0) too); the reference's ** calls libm's pow, within 0.52 ulp, which differs from it in
 * the last bit for about one step length in a thousand. */
void ct_fus_set_dt(const struct ct_ins *ins, double *Q, const double *dtk, double *ws, double dt)
{
    const int n = ins->n;
    double *A = ins->A;
    double ka = dtk[0] > 0.0 ? exp(-dt / dtk[0]) : 1.0;
    double kg = dtk[1] > 0.0 ? exp(-dt / dtk[1]) : 1.0;
    double go = dtk[3] * dt;
    double qv = dtk[2] * dt * dt, qo = go * go, qa = dtk[4] * dt, qg = dtk[5] * dt;
    int i;
    ws[CT_FS_DT_LAST] = dt;
    ws[CT_FS_KA] = ka;
    ws[CT_FS_KG] = kg;
    for (i = 0; i < 3; ++i) {                       /* strapdown.transition_static */
        A[(CT_POS + i) * n + CT_VEL + i] = dt;
        A[(CT_ACC + i) * n + CT_ACC + i] = ka;
        A[(CT_GYR + i) * n + CT_GYR + i] = kg;
    }
    for (i = 0; i < 3; ++i) {
        Q[(CT_VEL + i) * (n + 1)] = qv;
        Q[(CT_ORI + i) * (n + 1)] = qo;
        Q[(CT_ACC + i) * (n + 1)] = qa;
        Q[(CT_GYR + i) * (n + 1)] = qg;
    }
}

/* InertialPrediction.propagate + step_compiled: the step of the state ins over [t0, t1] with the
 * IMU ring's (itv, idv, icap slots) samples k - 1 and k, nring: the entries the ring holds; the
 * inputs at t0 and t1 interpolated linearly (offsets removed), the rate at mid-step; set_dt when
 * the step changed, then ct_ins_propagate.  The one step of the forward path (ct_fus_propagate)
 * and of the replay on the shadow (fusion.c). */
void ct_fus_step(const struct ct_ins *ins, double *Q, const double *dtk, double *ws, const int64_t *itv,
                 const double *idv, int64_t icap, int64_t k, int64_t nring, int64_t t0, int64_t t1)
{
    const double dt = (double)(t1 - t0) * 1e-6;
    const double *ba = ins->ba, *bg = ins->bg;
    const double *pd, *kd;
    double a0, a1, b0, b1, am, bm, in[15];
    const int64_t tk = itv[k];
    int64_t kp = k > 0 ? k - 1 : icap - 1;
    const int64_t tp = itv[kp];
    if (nring > 1 && tp < tk) {
        double span = 1.0 / (double)(tk - tp);
        a0 = (double)(t0 - tp) * span;
        a1 = (double)(t1 - tp) * span;
        if (a0 < 0.0)
            a0 = 0.0;
    } else {
        kp = k;
        a0 = a1 = 1.0;
    }
    b0 = 1.0 - a0;
    b1 = 1.0 - a1;
    pd = idv + kp * CT_IMU_WIDTH;
    kd = idv + k * CT_IMU_WIDTH;
    in[0] = b0 * pd[CT_IMU_F] + a0 * kd[CT_IMU_F] - ba[0];
    in[1] = b0 * pd[CT_IMU_F + 1] + a0 * kd[CT_IMU_F + 1] - ba[1];
    in[2] = b0 * pd[CT_IMU_F + 2] + a0 * kd[CT_IMU_F + 2] - ba[2];
    in[3] = b1 * pd[CT_IMU_F] + a1 * kd[CT_IMU_F] - ba[0];
    in[4] = b1 * pd[CT_IMU_F + 1] + a1 * kd[CT_IMU_F + 1] - ba[1];
    in[5] = b1 * pd[CT_IMU_F + 2] + a1 * kd[CT_IMU_F + 2] - ba[2];
    am = 0.5 * (a0 + a1);
    bm = 1.0 - am;
    in[6] = bm * pd[CT_IMU_W] + am * kd[CT_IMU_W] - bg[0];
    in[7] = bm * pd[CT_IMU_W + 1] + am * kd[CT_IMU_W + 1] - bg[1];
    in[8] = bm * pd[CT_IMU_W + 2] + am * kd[CT_IMU_W + 2] - bg[2];
    in[9] = b0 * pd[CT_IMU_FSRC] + a0 * kd[CT_IMU_FSRC];
    in[10] = b0 * pd[CT_IMU_FSRC + 1] + a0 * kd[CT_IMU_FSRC + 1];
    in[11] = b0 * pd[CT_IMU_FSRC + 2] + a0 * kd[CT_IMU_FSRC + 2];
    in[12] = b1 * pd[CT_IMU_FSRC] + a1 * kd[CT_IMU_FSRC];
    in[13] = b1 * pd[CT_IMU_FSRC + 1] + a1 * kd[CT_IMU_FSRC + 1];
    in[14] = b1 * pd[CT_IMU_FSRC + 2] + a1 * kd[CT_IMU_FSRC + 2];
    if (dt != ws[CT_FS_DT_LAST])
        ct_fus_set_dt(ins, Q, dtk, ws, dt);
    ct_ins_propagate((struct ct_ins *)ins, dt, in, ws[CT_FS_KA], ws[CT_FS_KG]);
}

/* InertialPrediction.propagate + step_compiled of the bound state (ct_fus_step) */
void ct_fus_propagate(const struct ct_fus_pred *f, int k, int nring, int64_t t0, int64_t t1)
{
    ct_fus_step(&f->ins, f->Q, f->dtk, f->st, f->itv, f->idv, f->icap, k, nring, t0, t1);
}

void ct_fus_to_source(const double *d, int moving, const double *p, const double *Th, double *hd)
{
    int i, j;
    if (!moving) {
        hd[CT_HIST_P] = p[0];
        hd[CT_HIST_P + 1] = p[1];
        hd[CT_HIST_P + 2] = p[2];
        for (i = 0; i < 9; ++i)
            hd[CT_HIST_R + i] = Th[i];
        return;
    }
    for (i = 0; i < 3; ++i) {
        double f0 = d[CT_IMU_PHI + i], f1 = d[CT_IMU_PHI + 3 + i], f2 = d[CT_IMU_PHI + 6 + i];
        hd[CT_HIST_P + i] = f0 * p[0] + f1 * p[1] + f2 * p[2];
        for (j = 0; j < 3; ++j)
            hd[CT_HIST_R + 3 * i + j] = f0 * Th[j] + f1 * Th[3 + j] + f2 * Th[6 + j];
    }
}

/* rotation.quat_from_elements: q = (w, x, y, z), w >= 0, of the row-major r[9] */
void ct_quat_from_elements(const double *r, double *q)
{
    double r00 = r[0], r01 = r[1], r02 = r[2], r10 = r[3], r11 = r[4], r12 = r[5], r20 = r[6],
           r21 = r[7], r22 = r[8];
    double t = r00 + r11 + r22, s, w, x, y, z, nn;
    if (t > 0.0) {
        s = sqrt(t + 1.0) * 2.0;
        w = 0.25 * s;
        x = (r21 - r12) / s;
        y = (r02 - r20) / s;
        z = (r10 - r01) / s;
    } else if (r00 > r11 && r00 > r22) {
        s = sqrt(1.0 + r00 - r11 - r22) * 2.0;
        w = (r21 - r12) / s;
        x = 0.25 * s;
        y = (r01 + r10) / s;
        z = (r02 + r20) / s;
    } else if (r11 > r22) {
        s = sqrt(1.0 + r11 - r00 - r22) * 2.0;
        w = (r02 - r20) / s;
        x = (r01 + r10) / s;
        y = 0.25 * s;
        z = (r12 + r21) / s;
    } else {
        s = sqrt(1.0 + r22 - r00 - r11) * 2.0;
        w = (r10 - r01) / s;
        x = (r02 + r20) / s;
        y = (r12 + r21) / s;
        z = 0.25 * s;
    }
    if (w < 0.0) {
        w = -w;
        x = -x;
        y = -y;
        z = -z;
    }
    nn = sqrt(w * w + x * x + y * y + z * z);
    q[0] = w / nn;
    q[1] = x / nn;
    q[2] = y / nn;
    q[3] = z / nn;
}

/* diag(M^T S M) of the symmetric 3x3 block S at row / column s0 of the n x n P; column c of M is
 * (m[c], m[3 + c], m[6 + c]) */
static void diag_congruence(const double *P, int n, int s0, const double *m, double *out)
{
    const double *r0 = P + (long)s0 * n + s0, *r1 = r0 + n, *r2 = r1 + n;
    double o00 = r0[0], o01 = r0[1], o02 = r0[2], o11 = r1[1], o12 = r1[2], o22 = r2[2];
    int c;
    for (c = 0; c < 3; ++c) {
        double x = m[c], y = m[3 + c], z = m[6 + c];
        out[c] = (x * (o00 * x + o01 * y + o02 * z) + y * (o01 * x + o11 * y + o12 * z)
                  + z * (o02 * x + o12 * y + o22 * z));
    }
}

void ct_fus_output(double *od, const double *hd, const double *P, int n, const double *Th, const double *d,
                   int moving, double status)
{
    od[CT_OUT_P] = hd[CT_HIST_P];
    od[CT_OUT_P + 1] = hd[CT_HIST_P + 1];
    od[CT_OUT_P + 2] = hd[CT_HIST_P + 2];
    ct_quat_from_elements(hd + CT_HIST_R, od + CT_OUT_Q);
    diag_congruence(P, n, CT_ORI, Th, od + CT_OUT_VAR_O);
    if (moving) {
        diag_congruence(P, n, CT_POS, d + CT_IMU_PHI, od + CT_OUT_VAR_P);
    } else {
        od[CT_OUT_VAR_P] = P[CT_POS * (n + 1)];
        od[CT_OUT_VAR_P + 1] = P[(CT_POS + 1) * (n + 1)];
        od[CT_OUT_VAR_P + 2] = P[(CT_POS + 2) * (n + 1)];
    }
    od[CT_OUT_STATUS] = status;
}

/* PoseOutput._status */
int ct_fus_status(int64_t age, int64_t stale_us, int64_t dr_after_us, int64_t dr_limit_us, int recovering,
                  int inconsistent)
{
    int status = 0;
    if (age > stale_us)
        status |= CT_OUT_STALE;
    if (age > dr_after_us) {
        status |= CT_OUT_DEAD_RECKONING;
        if (age > dr_limit_us)
            status |= CT_OUT_LOST;
    }
    if (recovering)
        status |= CT_OUT_RECOVERED;
    if (inconsistent)
        status |= CT_OUT_INCONSISTENT;
    return status;
}

/* OrientationFilter.predict after its time step (dt > 0): R <- R exp([(w - b) dt]x) (eq 2.27),
 * d <- c_d d (eq 2.7), a <- c_a a (eq 2.5), and the sums of the composed propagation */
void ct_ori_predict(const struct ct_ori_pred *o, double dt, double wx, double wy, double wz, double qwd)
{
    const double *b = o->bias;
    double *d = o->dist, *a = o->acc, *s = o->st;
    double cd = o->dist_corr, ca;
    ct_strapdown_rotate(o->R, (wx - b[0]) * dt, (wy - b[1]) * dt, (wz - b[2]) * dt, o->E);
    d[0] *= cd;
    d[1] *= cd;
    d[2] *= cd;
    ca = o->acc_corr_time_s > 0.0 ? exp(-dt / o->acc_corr_time_s) : 0.0;
    a[0] *= ca;
    a[1] *= ca;
    a[2] *= ca;
    s[CT_OA_CA] = ca;
    s[CT_OA_DT] += dt;
    s[CT_OA_INCL_DT] += dt;
    s[CT_OA_DT2] += dt * dt;
    s[CT_OA_CD] *= cd;
    s[CT_OA_QD] = s[CT_OA_QD] * cd * cd + qwd;
}

/* orientation_updates.skew_block: [v]x into the 3 rows of H (n columns) at column c */
static void skew_block(double *H, int n, int c, double x, double y, double z)
{
    H[c] = 0.0;
    H[c + 1] = -z;
    H[c + 2] = y;
    H[n + c] = z;
    H[n + c + 1] = 0.0;
    H[n + c + 2] = -x;
    H[2 * n + c] = -y;
    H[2 * n + c + 1] = x;
    H[2 * n + c + 2] = 0.0;
}

/* OrientationFilter.update_acc up to its propagation (eqs 2.20, 2.23): v = y_A - a-, the free-fall
 * test (0: free fall, _post_acc done, no update), else Inclination.update's y, H and R (1) */
int ct_ori_incl_begin(struct ct_ori_meas *o, double ax, double ay, double az, double motion_ms)
{
    const double *R = o->R, *a = o->a;
    double g = o->gravity, vx, vy, vz, vn, ca, zx, zy, zz, r;
    double *sc = o->sc;
    sc[CT_OS_AX] = ax;
    sc[CT_OS_AY] = ay;
    sc[CT_OS_AZ] = az;
    vx = ax - a[0];
    vy = ay - a[1];
    vz = az - a[2];
    vn = sqrt(vx * vx + vy * vy + vz * vz);
    if (!(fabs(vn - g) <= o->freefall_tolerance * g)) {
        ct_ori_post_acc(o);
        return 0;
    }
    ca = o->sums[CT_OA_CA];
    zx = R[6];
    zy = R[7];
    zz = R[8];
    o->iy[0] = vx / vn - zx;
    o->iy[1] = vy / vn - zy;
    o->iy[2] = vz / vn - zz;
    skew_block(o->iH, o->n, o->theta, (1.0 - ca) * zx, (1.0 - ca) * zy, (1.0 - ca) * zz);
    r = ((1.0 + ca * ca) * (o->acc_noise * o->acc_noise) + o->acc_motion_sigma * o->acc_motion_sigma
         + o->acc_adapt_gain * motion_ms) / (g * g);
    o->iR[0] = r;
    o->iR[4] = r;
    o->iR[8] = r;
    return 1;
}

/* OrientationFilter._apply: R <- R exp([theta]x), Rc <- R, b += db, d += dd */
void ct_ori_apply(const struct ct_ori_meas *o, const double *dx)
{
    int i;
    ct_strapdown_rotate(o->R, dx[o->theta], dx[o->theta + 1], dx[o->theta + 2], o->E);
    for (i = 0; i < 9; ++i)
        o->Rc[i] = o->R[i];
    for (i = 0; i < 3; ++i) {
        o->b[i] += dx[o->bias + i];
        o->d[i] += dx[o->dist + i];
    }
}

/* OrientationFilter._post_acc: a+ = y_A - g Z+ (eq 2.5) with the sample of ct_ori_incl_begin */
void ct_ori_post_acc(const struct ct_ori_meas *o)
{
    const double *R = o->R, *sc = o->sc;
    double g = o->gravity;
    o->a[0] = sc[CT_OS_AX] - g * R[6];
    o->a[1] = sc[CT_OS_AY] - g * R[7];
    o->a[2] = sc[CT_OS_AZ] - g * R[8];
}

/* Compass._heading_rows: the measurement turned to (Z x H_G, Z, their cross product) */
static void heading_rows(const struct ct_ori_meas *o, double zx, double zy, double zz, double hx, double hy,
                         double hz)
{
    double ax = zy * hz - zz * hy, ay = zz * hx - zx * hz, az = zx * hy - zy * hx, an, cx, cy, cz;
    double y0, y1, y2, *y = o->my, *H = o->mH;
    int n = o->n, t0 = o->theta, d0 = o->dist, c;
    an = sqrt(ax * ax + ay * ay + az * az);
    if (!(an > 1e-6))
        return;
    ax = ax / an;
    ay = ay / an;
    az = az / an;
    cx = ay * zz - az * zy;
    cy = az * zx - ax * zz;
    cz = ax * zy - ay * zx;
    y0 = y[0];
    y1 = y[1];
    y2 = y[2];
    y[0] = ax * y0 + ay * y1 + az * y2;
    y[1] = zx * y0 + zy * y1 + zz * y2;
    y[2] = cx * y0 + cy * y1 + cz * y2;
    for (c = 0; c < 3; ++c) {
        double h0 = H[t0 + c], h1 = H[n + t0 + c], h2 = H[2 * n + t0 + c];
        H[t0 + c] = ax * h0 + ay * h1 + az * h2;
        H[n + t0 + c] = zx * h0 + zy * h1 + zz * h2;
        H[2 * n + t0 + c] = cx * h0 + cy * h1 + cz * h2;
    }
    H[d0] = ax;
    H[d0 + 1] = ay;
    H[d0 + 2] = az;
    H[n + d0] = zx;
    H[n + d0 + 1] = zy;
    H[n + d0 + 2] = zz;
    H[2 * n + d0] = cx;
    H[2 * n + d0 + 1] = cy;
    H[2 * n + d0 + 2] = cz;
    o->mR[4] = 1.0;
    o->mR[8] = 1.0;
}

/* Compass.update up to its Kalman update (eqs 2.8-2.12, 2.21, 2.24): the driving noise of the
 * disturbance from the low-passed norm and dip, then y, H and R */
void ct_ori_compass_fill(const struct ct_ori_meas *o, double mx, double my, double mz)
{
    const double *R = o->R, *d = o->d, *hg = o->hg;
    double *cst = o->cst, *H = o->mH;
    double inv = 1.0 / cst[CT_CS_MREF], nx = mx * inv, ny = my * inv, nz = mz * inv;
    double gx = R[0] * nx + R[1] * ny + R[2] * nz;
    double gy = R[3] * nx + R[4] * ny + R[5] * nz;
    double gz = R[6] * nx + R[7] * ny + R[8] * nz;
    double al = o->dist_smoothing, norm, dip, sd, h0, h2, hx, hy, hz, r;
    int n = o->n, i, j;
    norm = (1.0 - al) * cst[CT_CS_NORM] + al * sqrt(gx * gx + gy * gy + gz * gz);
    dip = (1.0 - al) * cst[CT_CS_DIP] + al * atan2(gz, sqrt(gx * gx + gy * gy));
    sd = (o->dist_sigma + o->dist_norm_gain * fabs(norm - cst[CT_CS_NORM])
          + o->dist_dip_gain * fabs(dip - cst[CT_CS_DIP]));
    cst[CT_CS_QWD] = sd * sd;
    cst[CT_CS_NORM] = norm;
    cst[CT_CS_DIP] = dip;
    h0 = hg[0];
    h2 = hg[2];
    hx = R[0] * h0 + R[6] * h2;
    hy = R[1] * h0 + R[7] * h2;
    hz = R[2] * h0 + R[8] * h2;
    o->my[0] = nx - d[0] - hx;
    o->my[1] = ny - d[1] - hy;
    o->my[2] = nz - d[2] - hz;
    skew_block(H, n, o->theta, hx, hy, hz);
    if (o->heading_only)
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j)
                H[i * n + o->dist + j] = i == j ? 1.0 : 0.0;
    r = o->mag_noise * o->mag_noise;
    o->mR[0] = r;
    o->mR[4] = r;
    o->mR[8] = r;
    if (o->heading_only)
        heading_rows(o, R[6], R[7], R[8], hx, hy, hz);
}

/* SampleRing.nearest_slot: back from the newest sample to the first at or before t, compared
 * with the one after it */
static int64_t nearest_slot(const struct ct_quiet *q, int64_t head, int64_t count, int64_t t)
{
    int64_t slot = head, best = -1, i;
    for (i = 0; i < count; ++i) {
        slot -= 1;
        if (slot < 0)
            slot += q->cap;
        if (q->tv[slot] <= t) {
            if (best < 0 || t - q->tv[slot] < q->tv[best] - t)
                best = slot;
            break;
        }
        best = slot;
    }
    return best;
}

/* PulseGate.quiet */
static int pulse_quiet(const struct ct_quiet *q, int64_t t)
{
    int64_t j;
    for (j = 0; j < q->n; ++j)
        if (q->ps[j] - q->before <= t && t <= q->pe[j] + q->after)
            return 0;
    return 1;
}

/* track.burst_fusion.quiet_sample */
int64_t ct_quiet_sample(const struct ct_quiet *q, int64_t head, int64_t count, int64_t after_t, int64_t t_imu,
                        int64_t max_age_us)
{
    int64_t best = nearest_slot(q, head, count, t_imu), t, age;
    if (best < 0)
        return -1;
    t = q->tv[best];
    age = t - t_imu;
    if (age < 0)
        age = -age;
    if (t <= after_t || age > max_age_us)
        return -1;
    if ((q->fl[best] & CT_SAMPLE_SATURATED) || !pulse_quiet(q, t))
        return -1;
    return best;
}

/* track.burst_fusion.FlipOffset.observe: the set/reset offset from the jump across a flip, the
 * field turned back by the rate (rx, ry, rz) over the samples' interval (first order) */
void ct_flip_observe(double *fl, int64_t *fi, double gain, int64_t t_us, int state, double mx, double my,
                     double mz, double rx, double ry, double rz, int64_t max_dt_us)
{
    double *o = fl + CT_FL_O, *p = fl + CT_FL_PREV;
    if (state == fi[CT_FI_STATE]) {
        p[0] = mx;
        p[1] = my;
        p[2] = mz;
        fi[CT_FI_T] = t_us;
        return;
    }
    if (fi[CT_FI_STATE] >= 0 && 0 < t_us - fi[CT_FI_T] && t_us - fi[CT_FI_T] <= max_dt_us) {
        double dt = (double)(t_us - fi[CT_FI_T]) * 1e-6;
        double wx = rx * dt, wy = ry * dt, wz = rz * dt;
        double px = p[0], py = p[1], pz = p[2];
        double ex = px - (wy * pz - wz * py);
        double ey = py - (wz * px - wx * pz);
        double ez = pz - (wx * py - wy * px);
        double s = state ? 1.0 : -1.0;
        double k = (double)fi[CT_FI_N] < 1.0 / gain ? 1.0 / (double)(fi[CT_FI_N] + 1) : gain;
        o[0] += k * (0.5 * s * (mx - ex) - o[0]);
        o[1] += k * (0.5 * s * (my - ey) - o[1]);
        o[2] += k * (0.5 * s * (mz - ez) - o[2]);
        fi[CT_FI_N] += 1;
    }
    fi[CT_FI_STATE] = state;
    p[0] = mx;
    p[1] = my;
    p[2] = mz;
    fi[CT_FI_T] = t_us;
}

/* orientation_updates.Inclination.observe: the variance of y_A - g Z- about its running mean */
void ct_incl_observe(double *inc, const double *R, double gravity, double gain, double tau, double ax, double ay,
                     double az, double dt)
{
    double ex, ey, ez, k, v, *m = inc + CT_IN_MEAN;
    if (!(gain > 0.0))
        return;
    ex = ax - gravity * R[6];
    ey = ay - gravity * R[7];
    ez = az - gravity * R[8];
    k = tau > 0.0 ? dt / tau : 1.0;
    k = k < 1.0 ? k : 1.0;
    if (inc[CT_IN_STARTED] == 0.0) {
        k = 1.0;
        inc[CT_IN_STARTED] = 1.0;
    }
    m[0] += k * (ex - m[0]);
    m[1] += k * (ey - m[1]);
    m[2] += k * (ez - m[2]);
    inc[CT_IN_SQ] += k * (ex * ex + ey * ey + ez * ez - inc[CT_IN_SQ]);
    v = inc[CT_IN_SQ] - (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
    inc[CT_IN_MOTION] = v > 0.0 ? v : 0.0;
}

/* ekf.symmetrize: P <- (P + P^T) / 2 through the scratch T (the same additions and halvings) */
void ct_symmetrize(int n, double *P, double *T)
{
    int i, j;
    memcpy(T, P, sizeof(double) * (size_t)n * (size_t)n);
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j)
            P[i * n + j] = (T[i * n + j] + T[j * n + i]) * 0.5;
}

/* OrientationFilter.propagate (compiled) with CovariancePredict.after_predict's symmetrisation and
 * _restart_sums; 1 when it ran */
static int ori_propagate(const struct ct_ori_step *o, int64_t count)
{
    double *s = o->pred.st;
    if (s[CT_OA_DT] <= 0.0)
        return 0;
    ct_orientation_propagate(&o->prop, s[CT_OA_DT], s[CT_OA_DT2], s[CT_OA_CD], s[CT_OA_QD]);
    if ((count + 1) % o->symmetrize_every == 0)
        ct_symmetrize(o->prop.n, o->prop.P, o->prop.T);
    s[CT_OA_DT] = s[CT_OA_DT2] = s[CT_OA_QD] = 0.0;
    s[CT_OA_CD] = 1.0;
    return 1;
}

int ct_ori_propagate_now(const struct ct_ori_step *o, int64_t count)
{
    return ori_propagate(o, count);
}

/* KalmanUpdate.update (compiled) with its symmetrisation after the count-th accepted update */
static int ori_kalman(const struct ct_ori_step *o, const struct ct_kalman *u, double gate, double *nis,
                      int64_t count)
{
    int flags = ct_kalman_update(u, o->prop.P, gate, nis);
    if (flags == CT_EKF_OK && (count + 1) % o->symmetrize_every == 0)
        ct_symmetrize(o->prop.n, o->prop.P, o->prop.T);
    return flags;
}

/* ct_ori_sample up to its prediction (the compass sample with its set/reset offset into m[CT_OM_*]) */
int ct_ori_sample_begin(const struct ct_ori_step *o, int64_t t, double wx, double wy, double wz, int64_t t_prev,
                        int64_t head, int64_t count, double *m)
{
    const double *b = o->pred.bias, *fo = o->fl + CT_FL_O;
    double dt;
    int64_t slot = ct_quiet_sample(&o->q, head, count, o->ct[0], t, o->max_age_us);
    m[CT_OM_FOUND] = 0.0;
    if (slot >= 0) {                                        /* _Ori.step: the compass sample */
        int st = (o->q.fl[slot] & CT_SAMPLE_FLIP) ? 1 : 0;
        double sg, mx, my, mz;
        o->ct[0] = o->q.tv[slot];
        mx = o->mb[3 * slot];
        my = o->mb[3 * slot + 1];
        mz = o->mb[3 * slot + 2];
        ct_flip_observe(o->fl, o->fi, o->flip_gain, o->ct[0], st, mx, my, mz, wx - b[0], wy - b[1], wz - b[2],
                        o->max_age_us);
        sg = st ? 1.0 : -1.0;
        m[CT_OM_FOUND] = 1.0;
        m[CT_OM_X] = mx - sg * fo[0];
        m[CT_OM_Y] = my - sg * fo[1];
        m[CT_OM_Z] = mz - sg * fo[2];
    }
    dt = (double)(t - t_prev) * 1e-6;                        /* OrientationFilter.predict */
    if (dt > 0.0) {
        ct_ori_predict(&o->pred, dt, wx, wy, wz, o->meas.cst[CT_CS_QWD]);
        return CT_OS_PREDICTED;
    }
    return 0;
}

/* ct_ori_sample after its prediction (and the caller's orthonormalisation): the update round */
int ct_ori_sample_end(const struct ct_ori_step *o, double ax, double ay, double az, int n, const double *m,
                      int64_t pcount, int64_t icount, int64_t mcount)
{
    struct ct_ori_meas *me = (struct ct_ori_meas *)&o->meas;
    double *s = o->pred.st;
    int r = 0, nprop = 0, flags;
    if (n + 1 < o->every)
        return r;
    r |= CT_OS_ROUND;                                       /* update_acc */
    ct_incl_observe(o->inc, o->pred.R, me->gravity, me->acc_adapt_gain, o->acc_adapt_tau_s, ax, ay, az,
                    s[CT_OA_INCL_DT]);
    s[CT_OA_INCL_DT] = 0.0;
    if (!ct_ori_incl_begin(me, ax, ay, az, o->inc[CT_IN_MOTION])) {
        r |= CT_OS_FREEFALL;
    } else {
        nprop += ori_propagate(o, pcount + nprop);
        flags = ori_kalman(o, &o->iu, o->igate, o->inis, icount);
        if (flags == CT_EKF_OK)
            ct_ori_apply(me, me->idx);
        ct_ori_post_acc(me);
        r |= CT_OS_ACC | (flags << CT_OS_ACC_SHIFT);
    }
    if (m[CT_OM_FOUND] != 0.0) {                            /* update_mag (the compass has learned) */
        ct_ori_compass_fill(me, m[CT_OM_X], m[CT_OM_Y], m[CT_OM_Z]);
        nprop += ori_propagate(o, pcount + nprop);
        flags = ori_kalman(o, &o->mu, o->mgate, o->mnis, mcount);
        if (flags == CT_EKF_OK)
            ct_ori_apply(me, me->mdx);
        r |= CT_OS_MAG | (flags << CT_OS_MAG_SHIFT);
    }
    return r | (nprop << CT_OS_PROP_SHIFT);
}

int ct_ori_sample(const struct ct_ori_step *o, int64_t t, double ax, double ay, double az, double wx, double wy,
                  double wz, int64_t t_prev, int n, int64_t head, int64_t count, int64_t pcount, int64_t icount,
                  int64_t mcount)
{
    double m[CT_OM_N];
    int r = ct_ori_sample_begin(o, t, wx, wy, wz, t_prev, head, count, m);
    return r | ct_ori_sample_end(o, ax, ay, az, n, m, pcount, icount, mcount);
}

/* orientation.OrientationFilter._orthonormalize: R <- R (3 I - R^T R) / 2, one Newton step of the polar
 * factor.  T as the reference's loop computes it, (1.5 or 0.0) - 0.5 (R^T R)_ij; the product R T as the
 * reference's np.matmul computes a 3x3 product here (its BLAS's dgemm kernel, OpenBLAS Haswell and later:
 * each element an FMA chain over k = 0, 1, 2 from the first product, then added to the zeroed output,
 * beta = 0), so R's bits are the reference's. */
void ct_ori_orthonormalize(double *R)
{
    double T[9], O[9];
    int i, j;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            double rtr = R[i] * R[j] + R[3 + i] * R[3 + j] + R[6 + i] * R[6 + j];
            T[3 * i + j] = (i == j ? 1.5 : 0.0) - 0.5 * rtr;
        }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            O[3 * i + j] = 0.0 + fma(R[3 * i + 2], T[6 + j], fma(R[3 * i + 1], T[3 + j], R[3 * i] * T[j]));
    memcpy(R, O, sizeof(O));
}

/* ct_ori_sample of a sample whose prediction may be the filter's 64th step (steps: OrientationFilter.steps
 * before it): when it predicts and (steps + 1) & 63 is 0, R orthonormalised after the prediction, before
 * the update round (OrientationFilter._predict_compiled's order; the decays between do not read R) */
int ct_ori_sample_ortho(const struct ct_ori_step *o, int64_t t, double ax, double ay, double az, double wx,
                        double wy, double wz, int64_t t_prev, int n, int64_t head, int64_t count, int64_t pcount,
                        int64_t icount, int64_t mcount, int64_t steps)
{
    double m[CT_OM_N];
    int r = ct_ori_sample_begin(o, t, wx, wy, wz, t_prev, head, count, m);
    if ((r & CT_OS_PREDICTED) && ((steps + 1) & CT_ORI_ORTHO_MASK) == 0)
        ct_ori_orthonormalize(o->pred.R);
    return r | ct_ori_sample_end(o, ax, ay, az, n, m, pcount, icount, mcount);
}

/* ring.Ring.push: the next slot gets time t; a full ring overwrites its oldest entry */
int64_t ct_ring_push(int64_t *hc, int64_t cap, int64_t *tv, int64_t t)
{
    int64_t p = hc[0], n = p + 1;
    tv[p] = t;
    hc[0] = n == cap ? 0 : n;
    if (hc[1] < cap)
        hc[1] += 1;
    return p;
}

/* ring.Ring.pop: the oldest entry's slot, or -1 when empty */
int64_t ct_ring_pop(int64_t *hc, int64_t cap)
{
    int64_t p;
    if (hc[1] == 0)
        return -1;
    p = hc[0] - hc[1];
    if (p < 0)
        p += cap;
    hc[1] -= 1;
    return p;
}

/* measure.imu.ImuRing.push (ct_fusimu.h) */
void ct_imu_ring_push(int64_t *hc, int64_t cap, int64_t *tv, double *d, int64_t *st, int64_t t, const double *s,
                      double acc_lsb, double gyr_lsb)
{
    int64_t k;
    if (t <= st[CT_IR_LAST_T]) {                 /* not newer than the previous sample: refused */
        st[CT_IR_DROPPED] += 1;
        return;
    }
    st[CT_IR_LAST_T] = t;
    if (hc[1] == cap)
        st[CT_IR_DROPPED] += 1;
    k = ct_ring_push(hc, cap, tv, t);
    d += 6 * k;
    d[0] = s[0] * acc_lsb;
    d[1] = s[1] * acc_lsb;
    d[2] = s[2] * acc_lsb;
    d[3] = s[3] * gyr_lsb;
    d[4] = s[4] * gyr_lsb;
    d[5] = s[5] * gyr_lsb;
    st[CT_IR_RECEIVED] += 1;
}

/* track.burst_fusion._Ori.settled and magnetic_inertial.FusionFilter.live_ready at t (a pending
 * snapshot inside the step: CT_SR_SNAP where no replay runs, FusionFilter._advance's split_take), then
 * the orthonormalisation's test ((steps + 1) & 63: a sample whose prediction may be the 64th) */
int ct_sample_route(const struct ct_sample_state *s, int64_t t)
{
    const int64_t *of = s->of, *ff = s->ff;
    int64_t t0;
    if (!(of[CT_OF_INIT] && t - of[CT_OF_T] <= s->gap_us && !s->learn[0]))
        return CT_SR_SLOW;
    t0 = s->ts[0];
    if (!(ff[CT_FF_INIT] && t0 < t && t - t0 <= s->max_gap_us && !ff[CT_FF_RECORDER]))
        return CT_SR_SLOW;
    if (s->sq[CT_SQ_PENDING] && t0 < s->sq[CT_SQ_T] && s->sq[CT_SQ_T] <= t)   /* Snapshot.due */
        return ff[CT_FF_REPLAYING] ? CT_SR_SLOW : CT_SR_SNAP;
    if (((of[CT_OF_STEPS] + 1) & CT_ORI_ORTHO_MASK) == 0)
        return CT_SR_ORTHO;
    return CT_SR_WHOLE;
}

/* ekf.KalmanUpdate.counted: the count or the rejection; flags */
static int64_t ct_counted(int64_t *k, int64_t flags)
{
    if (flags != CT_EKF_OK)
        k[1] += 1;
    else
        k[0] += 1;
    return flags;
}

void ct_sample_done(const struct ct_sample_state *s, int64_t t, int r)
{
    s->fpc[0] += 1;                                     /* InertialPrediction.sampled */
    s->ps[0] += 1;
    s->ts[0] = t;
    ct_sample_done_ori(s, t, r);
}

void ct_sample_done_ori(const struct ct_sample_state *s, int64_t t, int r)
{
    int64_t *of = s->of;
    of[CT_OF_T] = t;                                    /* OrientationFilter.sample_done */
    of[CT_OF_STEPS] += r & CT_OS_PREDICTED;
    if (r & CT_OS_ROUND) {
        if (r & (CT_OS_FREEFALL | CT_OS_ACC))
            of[CT_OF_ACCF] = (r & CT_OS_FREEFALL) ? CT_ORI_FREEFALL : ct_counted(s->ik, (r >> CT_OS_ACC_SHIFT) & 15);
        s->opc[0] += r >> CT_OS_PROP_SHIFT;
        if (r & CT_OS_MAG)
            of[CT_OF_MAGF] = ct_counted(s->mk, (r >> CT_OS_MAG_SHIFT) & 15);
        s->ns[0] = 0;                                   /* _Ori.sampled */
        if (r & CT_OS_MAG)
            s->ns[1] += 1;
    } else {
        s->ns[0] += 1;
    }
}
