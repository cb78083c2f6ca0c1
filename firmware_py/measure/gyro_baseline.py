"""Pulse extraction with the baseline turned by the gyroscope.

The earth field is constant in the world frame; a sensor that turns during a
pulse window sees it turn the other way in its own frame. The linear baseline
of :mod:`coiltrack.firmware.measure.pulse` removes only the linear part of
that change ("movement within a cycle makes the DC component vary", thesis
``seeds/002_cd7f1fdb7fc67471.txt`` sec. 5.4, Fig. 5.6); what is left is about
``|B_e| w^2 t^2 / 2`` over the window: at 40 deg/s and +-65 ms against a
0.4 uT pulse at 45 cm, 49 uT x 0.5 x (0.7 rad/s x 0.065 s)^2 = 50 nT per side,
tens of percent of the amplitude once the linear fit spreads it.

Here every magnetometer sample of the window (``y(t)``, sensor frame at
``t``) is first turned into the sensor frame at the window's first sample
``t_a`` with the rotation the gyroscope gives over ``[t_a, t]``:

    ``dR/dt = R [w]x``  (``R(t)``: sensor frame at ``t`` to the one at ``t_a``;
    ``w`` the gyroscope rate, sensor frame, rad/s; the strapdown of thesis
    eq 2.27 without the orientation itself)

    ``y_a(t) = R(t) y(t)``: the earth field ``R_w(t)^T B_e = R(t)^T b_a`` becomes
    the constant ``b_a``; a coil field fixed in the source frame also becomes
    constant if the sensor only turns.

The unchanged extractor (flags, linear baseline, variances) then runs on the
turned samples, and the amplitude is turned back into the sensor frame at
``t_m``: ``amp = R(t_m)^T amp_a``, the frame the pose solver and the motion
compensation take the window's signal in (``t_m`` is the middle of the
first and last used in-pulse samples, the window's ``pulse_mid``; the middle
of the settled window when it has none). Whatever the gyroscope does not
explain (its offset: a rotation linear in time, below 1e-3 rad over a window
at 0.02 rad/s, translation in a non-uniform field) is again removed to first
order by the linear baseline.

Integration: the rate is the gyroscope samples' linear interpolation (held
at the ends); each interval between consecutive magnetometer samples (and
the instant ``t_m``) is one exact rotation-vector step at the interval's mid
rate. A constant rate is integrated exactly. Work per window: one step per
span sample (at most the scratch ring's capacity); everything is allocated
in ``__init__``.
"""
from __future__ import annotations

import math
import operator

from coiltrack.protocol.schema import GYR_LSB

from coiltrack.firmware.measure.pulse import NO_TIME_US, PulseExtractor, SampleRing
from coiltrack.firmware.ring import Ring


class GyroRing(Ring):
    """The sensor node's gyroscope rates (rad/s, sensor frame) for the window
    closer, by time (us). Samples not newer than the previous one, or not
    finite, are refused (counted in ``rejected``); a full ring drops its
    oldest sample."""

    def __init__(self, capacity: int):
        super().__init__(capacity, (("W", 3),))
        self._latest = NO_TIME_US
        self.rejected = 0

    def push_rate(self, t_us: int, wx: float, wy: float, wz: float) -> None:
        """One rate sample (rad/s) at ``t_us``."""
        if (t_us <= self._latest
                or not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz))):
            self.rejected += 1
            return
        k = Ring.push(self, t_us)
        d = self.dv
        d[k, 0] = wx
        d[k, 1] = wy
        d[k, 2] = wz
        self._latest = t_us

    def push(self, msg) -> None:
        """An ``IMU_SAMPLE`` (gyroscope counts of ``GYR_LSB`` rad/s)."""
        self.push_rate(msg.t_us, msg.gx * GYR_LSB, msg.gy * GYR_LSB, msg.gz * GYR_LSB)


class GyroBaselineExtractor(PulseExtractor):
    """:class:`~coiltrack.firmware.measure.pulse.PulseExtractor` on samples
    turned by the gyroscope (see the module docstring).

    ``gyro`` is the node's :class:`GyroRing`; ``span_capacity`` bounds the
    samples one window reads (its bracketing samples included): a window
    with more is flagged ``PULSE_INCOMPLETE`` as an unbracketed one. A
    window whose span the rates do not reach to within ``gyro_gap_us`` at
    either end (the IMU stream stopped or not yet started) is extracted by
    the base extractor (counted in ``plain_windows``).
    Keyword arguments are the base extractor's.
    """

    def __init__(self, ring: SampleRing, gyro: GyroRing, span_capacity: int, gyro_gap_us: int = 50_000, **kw):
        super().__init__(ring, **kw)
        self._src = ring
        self._gyro = gyro
        self._gap = operator.index(gyro_gap_us)
        self.plain_windows = 0         # windows the gyroscope did not cover: extracted as by the base
        self._turned = SampleRing(operator.index(span_capacity) + 2)
        self.turned_windows = 0        # windows whose samples were turned with gyroscope rates
        self.max_angle_rad = 0.0       # largest rotation over a window seen so far (diagnostic)
        self._cur = 0                  # gyro interpolation cursor (logical index)

    # ------------------------------------------------------------ rates
    def _rate_at(self, t: float):
        """Interpolated gyroscope rate at ``t`` (us, non-decreasing between
        calls within a window); held beyond the ends, zero without samples."""
        g = self._gyro
        n = len(g)
        if n == 0:
            return 0.0, 0.0, 0.0
        tv = g.tv
        dv = g.dv
        i = self._cur
        while i < n and tv[g.slot(i)] < t:
            i += 1
        self._cur = i
        if i == 0:
            k = g.slot(0)
            return dv[k, 0], dv[k, 1], dv[k, 2]
        if i == n:
            k = g.slot(n - 1)
            return dv[k, 0], dv[k, 1], dv[k, 2]
        k0 = g.slot(i - 1)
        k1 = g.slot(i)
        t0 = tv[k0]
        t1 = tv[k1]
        u = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
        v = 1.0 - u
        return (v * dv[k0, 0] + u * dv[k1, 0], v * dv[k0, 1] + u * dv[k1, 1],
                v * dv[k0, 2] + u * dv[k1, 2])

    def _step(self, q, t0: int, t1: int):
        """``q`` (w, x, y, z) advanced from ``t0`` to ``t1`` (us) by ``R <- R exp([w dt]x)``
        at the interval's mid rate."""
        if t1 <= t0:
            return q
        dt = (t1 - t0) * 1e-6
        wx, wy, wz = self._rate_at(0.5 * (t0 + t1))
        rx, ry, rz = wx * dt, wy * dt, wz * dt
        a = math.sqrt(rx * rx + ry * ry + rz * rz)
        if a < 1e-12:
            return q
        s = math.sin(0.5 * a) / a
        cw, cx, cy, cz = math.cos(0.5 * a), rx * s, ry * s, rz * s
        qw, qx, qy, qz = q
        return (qw * cw - qx * cx - qy * cy - qz * cz,
                qw * cx + qx * cw + qy * cz - qz * cy,
                qw * cy - qx * cz + qy * cw + qz * cx,
                qw * cz + qx * cy - qy * cx + qz * cw)

    # ------------------------------------------------------------ extraction
    def extract(self, start_us: int, end_us: int, amp_out, var_out) -> tuple[int, int, int]:
        """As the base extractor's, on the turned samples; ``amp_out`` in the
        sensor frame at ``t_m``, the middle of the used in-pulse samples."""
        src = self._src
        self._turned.clear()
        try:
            start = operator.index(start_us)
            end = operator.index(end_us)
        except TypeError:
            self._ring = src
            return PulseExtractor.extract(self, start_us, end_us, amp_out, var_out)
        if len(src) == 0 or len(self._gyro) == 0:
            self._ring = src
            return PulseExtractor.extract(self, start, end, amp_out, var_out)
        a, b = self._copied_span(start, end)
        g = self._gyro
        gt = g.tv
        if (gt[g.slot(0)] > src.tv[src.slot(a)] + self._gap
                or gt[g.slot(len(g) - 1)] < src.tv[src.slot(b)] - self._gap):
            self.plain_windows += 1               # the rates do not cover the window: the linear baseline
            self._ring = src
            return PulseExtractor.extract(self, start, end, amp_out, var_out)
        q_m = self._turn(a, b, self._mid_time(start, end))
        ang = 2.0 * math.acos(min(1.0, abs(q_m[0])))
        if ang > self.max_angle_rad:
            self.max_angle_rad = ang
        self.turned_windows += 1
        self._ring = self._turned
        try:
            res = PulseExtractor.extract(self, start, end, amp_out, var_out)
        finally:
            self._ring = src
        # back into the sensor frame at t_m: amp = R(t_m)^T amp_a
        qw, qx, qy, qz = q_m
        x, y, z = _rotate((qw, -qx, -qy, -qz), amp_out[0], amp_out[1], amp_out[2])
        amp_out[0] = x
        amp_out[1] = y
        amp_out[2] = z
        return res

    def _copied_span(self, start: int, end: int) -> tuple[int, int]:
        """Logical indices ``[a, b]`` of the source samples the window reads, the bracketing
        samples included (the newest that fit the turned ring when more than one window holds)."""
        src = self._src
        n = len(src)
        lo, hi = self.span(start, end)
        i_lo = src.index_at_or_after(lo)
        i_hi = src.index_at_or_after(hi + 1)
        a = i_lo - 1 if i_lo > 0 else 0
        b = i_hi if i_hi < n else n - 1
        if b - a + 1 > self._turned.capacity:
            a = b - self._turned.capacity + 1
        return a, b

    def _mid_time(self, start: int, end: int) -> int:
        """``t_m``: the middle of the used in-pulse samples (the window's ``pulse_mid``), or of the
        settled window when it holds none."""
        src = self._src
        n = len(src)
        u0 = src.index_at_or_after(start + self._settle_us)
        p_first = src.index_at_or_after(start)
        if u0 <= p_first:
            u0 = p_first + 1
        u1 = src.index_at_or_after(end - self._guard_us + 1) - 1
        p_last = src.index_at_or_after(end + 1) - 1
        if u1 >= p_last:
            u1 = p_last - 1
        if 0 <= u0 <= u1 < n:
            return (src.tv[src.slot(u0)] + src.tv[src.slot(u1)]) // 2
        return (start + self._settle_us + end - self._guard_us) // 2

    def _turn(self, a: int, b: int, t_m: int):
        """Copy the source samples ``[a, b]`` into the turned ring, each rotated by the attitude
        integrated from the first (the gyroscope's rates); returns the attitude at ``t_m``."""
        src = self._src
        out = self._turned
        g = self._gyro
        tv = src.tv
        bv = src.bv
        fv = src.fv
        self._cur = g.index_at_or_after(tv[src.slot(a)])
        if self._cur > 0:
            self._cur -= 1
        q = (1.0, 0.0, 0.0, 0.0)
        q_m = q
        t_prev = tv[src.slot(a)]
        have_m = t_m < t_prev
        for i in range(a, b + 1):
            p = src.slot(i)
            t = tv[p]
            if not have_m and t >= t_m:
                q = self._step(q, t_prev, t_m)
                q_m = q
                have_m = True
                t_prev = t_m
            q = self._step(q, t_prev, t)
            t_prev = t
            j = 3 * p
            x, y, z = _rotate(q, bv[j], bv[j + 1], bv[j + 2])
            f = fv[p]
            out.push(t, x, y, z, bool(f & 1), (f >> 1) & 1)
        if not have_m:                            # t_m after the last sample (an incomplete window)
            q_m = self._step(q, t_prev, t_m)
        return q_m


def _rotate(q, vx: float, vy: float, vz: float):
    """``R(q) v`` for the unit quaternion ``q = (w, x, y, z)``."""
    w, ux, uy, uz = q
    # t = 2 u x v; v' = v + w t + u x t
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return (vx + w * tx + uy * tz - uz * ty,
            vy + w * ty + uz * tx - ux * tz,
            vz + w * tz + ux * ty - uy * tx)
