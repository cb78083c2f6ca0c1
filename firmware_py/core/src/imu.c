/*
 * The receive stage's IMU decode: the compiled form of coiltrack.firmware.receive (_clipped and
 * Receiver._delta), the integer and floating-point operations of the Python in the same order.
 *
 * An IMU_DELTA pair (delta angle, then delta velocity, one 14-bit stamp; each axis the node's
 * running sum wrapped to 16 bits) becomes n = round(T imu_rate) samples of the mean rate
 * dtheta / T and mean specific force dv / T (in GYR_LSB / ACC_LSB counts), T the time between
 * this pair's stamp and the previous one's (receive.py's module docstring).  The node's state is
 * a caller-owned row of CT_DELTA_NST int64 (one row per node id, allocated at start-up).
 */
#include <math.h>
#include <stdint.h>

#include "coiltrack_core.h"

/* _clipped: an axis at the clip code (IMU_CLIP_COUNTS or beyond) */
int ct_imu_clipped(const int64_t *v6)
{
    int i;
    for (i = 0; i < 6; ++i)
        if (v6[i] >= CT_IMU_CLIP || v6[i] <= -CT_IMU_CLIP)
            return 1;
    return 0;
}

/* _d16: a - b of two wrapped 16-bit sums */
static int64_t ct_d16(int64_t a, int64_t b)
{
    return ((a - b + 32768) & 0xFFFF) - 32768;
}

/* Python's floor division by a positive b */
static int64_t ct_floordiv(int64_t a, int64_t b)
{
    int64_t q = a / b;
    return (a % b != 0 && a < 0) ? q - 1 : q;
}

/* protocol.schema.unwrap_stamp: the master time of a 14-bit stamp received at now_us */
int64_t ct_unwrap_stamp(int64_t stamp, int64_t now_us)
{
    int64_t r = ct_floordiv(now_us + CT_STAMP_LEAD_US, CT_STAMP_LSB_US);
    int64_t lo = r - CT_STAMP_MASK;
    return (lo + ((stamp - lo) & CT_STAMP_MASK)) * CT_STAMP_LSB_US;
}

/* Receiver._delta for one IMU_DELTA frame (x, y, z, stamp) of the node whose state is st:
 * returns the number of IMU steps of a completed pair (out: gx, gy, gz, ax, ay, az, step_us;
 * io[CT_DIO_T0]: the interval's start), else 0; the counters in io are advanced as the Python's */
int ct_imu_delta(int64_t *st, int64_t x, int64_t y, int64_t z, int64_t s, int64_t now_us, double interval_us,
                 double step_us, double *out, int64_t *io)
{
    int64_t t_end, last, has_last, dax, day, daz, dvx, dvy, dvz, d;
    double T, q, ka, kv;
    int64_t n;
    if (!(s & CT_STAMP_DVEL)) {
        if (st[CT_D_PENDING])
            io[CT_DIO_UNPAIRED] += 1;
        st[CT_D_STAMP] = s & CT_STAMP_MASK;
        st[CT_D_X] = x;
        st[CT_D_Y] = y;
        st[CT_D_Z] = z;
        st[CT_D_PENDING] = 1;
        st[CT_D_SAT] = (s & CT_STAMP_SATURATED) != 0;
        return 0;
    }
    if (!st[CT_D_PENDING] || st[CT_D_STAMP] != (s & CT_STAMP_MASK)) {
        io[CT_DIO_UNPAIRED] += 1;
        st[CT_D_PENDING] = 0;
        return 0;
    }
    st[CT_D_PENDING] = 0;
    t_end = ct_unwrap_stamp(st[CT_D_STAMP], now_us);
    last = st[CT_D_LAST];
    has_last = st[CT_D_HAS_LAST];
    dax = ct_d16(st[CT_D_X], st[CT_D_AX]);
    day = ct_d16(st[CT_D_Y], st[CT_D_AY]);
    daz = ct_d16(st[CT_D_Z], st[CT_D_AZ]);
    dvx = ct_d16(x, st[CT_D_VX]);
    dvy = ct_d16(y, st[CT_D_VY]);
    dvz = ct_d16(z, st[CT_D_VZ]);
    st[CT_D_LAST] = t_end;
    st[CT_D_HAS_LAST] = 1;
    st[CT_D_AX] = st[CT_D_X];
    st[CT_D_AY] = st[CT_D_Y];
    st[CT_D_AZ] = st[CT_D_Z];
    st[CT_D_VX] = x;
    st[CT_D_VY] = y;
    st[CT_D_VZ] = z;
    d = t_end - last;
    if (!has_last || !(0 < d && (double)d <= 3.5 * interval_us)) {
        io[CT_DIO_ANCHORS] += 1;
        return 0;
    }
    T = (double)d;
    q = rint(T / step_us);                   /* Python's round: half to even */
    n = (int64_t)q;
    if (n < 1)
        n = 1;
    if (st[CT_D_SAT] || (s & CT_STAMP_SATURATED)) {
        io[CT_DIO_SAT_PAIRS] += 1;
        io[CT_DIO_SATURATED] += n;
        return 0;
    }
    io[CT_DIO_T0] = t_end - (int64_t)rint(T);
    out[6] = T / (double)n;
    ka = CT_DANG_LSB_RAD / (T * 1e-6 * CT_GYR_LSB);
    kv = CT_DVEL_LSB_MPS / (T * 1e-6 * CT_ACC_LSB);
    out[0] = (double)dax * ka;
    out[1] = (double)day * ka;
    out[2] = (double)daz * ka;
    out[3] = (double)dvx * kv;
    out[4] = (double)dvy * kv;
    out[5] = (double)dvz * kv;
    io[CT_DIO_DELTAS] += 1;
    return (int)n;
}
