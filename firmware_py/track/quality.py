"""The quality figure of every POSE: 0-255, 255 best (like Polhemus Viper's distortion level and
trakSTAR's quality number): an estimate of the pose's position error from what the track stage
knows about it, mapped onto a byte.

The estimated error (m) of a pose solved from one X, Y, Z burst is

    ``e^2 = trace(P_pos) max(1, x) + |dp_motion|^2``

with three parts:

* ``P_pos``: the solve's own position covariance, the Cramer-Rao-like ``(H^T W H)^-1`` of
  ``pose.covariance``: how far the noise alone moves the pose there (it grows as ``r^8`` with the
  range, so it carries the ranking wherever the noise dominates);
* ``dp_motion``: the position error the sensor's motion *within the burst* makes. The solver
  takes the three pulses as one still pose, but pulse ``j`` is measured ``d_j`` seconds from the
  burst's middle, so its column of signals is ``h_j(x) + d_j H_j xdot`` (first order;
  ``H_j`` the Jacobian of Schepers & Veltink ``seeds/000_e46ec0e8bf7ea271.txt`` eqs 9-11, ``xdot``
  the velocity in the source frame and the sensor-frame rate of turn). The least-squares pose
  absorbs ``dx = P H^T W u``, ``u = D H xdot``, ``D = diag(d_j)`` (the linearised solve), and
  its position part is ``dp_motion``. Thesis ``seeds/002_cd7f1fdb7fc67471.txt`` sec 6.5 names
  this relative motion during the burst as the main error source of the pulsed tracker; the
  fusion pipeline compensates it with the IMU (``track.burst_fusion``) but the magnetic POSE and
  its quality come from the uncompensated solve, and a magnetic-only tracker has no IMU at
  all. ``xdot`` is taken from the node's previous magnetic solution (one cycle earlier:
  ``(p - p_prev) / dt`` and ``log(R_prev^T R) / dt``; none after a gap of more than two cycles,
  the first pose, or AC excitation, whose coils are measured at once; a pose that jumped from
  the previous one gets a large motion term and a low quality, one of the two being wrong). The
  motion's effect depends on its direction against the geometry (a tangential move at close
  range changes the three columns quite differently from a radial one), which is why the
  magnitude ``|v| t_rms`` alone does not rank it: measured on ``imperfect-fusion`` (calibrated, seed 4, 60 s) the
  linearised ``|dp_motion|`` with the true motion ranks the error with Spearman 0.93, ``|v|``
  and ``|w| r`` times the burst's rms time with 0.25;
* ``x = x_fit + x_nis + x_quiet``, the pose's inconsistency beyond the noise (~1 when everything
  fits to it), inflating ``P_pos`` the usual way a least-squares covariance is inflated by its
  reduced chi-square:

  - the fit's residual: the solver's weighted cost ``chi2 = sum ((S - h) / sigma)^2`` (eq 5 is
    the model ``h``) less ``chi2_motion``, the part of the residual the motion above explains
    (``u - H dx`` weighted), over ``dof = 3 n - 6``: a residual left by metal or a wrong
    calibration, which the pose partly absorbs as well. Without the subtraction the motion
    counted twice (once as ``dp_motion``, once as a residual inflating ``P_pos``), and at close
    range, where a few millimetres of motion leave a residual of hundreds of ``sigma`` on a
    pose whose noise is a tenth of a millimetre, the quality followed the residual against the
    error;
  - the fusion filter's normalised innovation squared per dimension, ``x_nis = NIS / m``, when
    the tracker has one (``estimate.ekf``; 0 otherwise);
  - the quiet field's consistency: the newest magnetometer sample after the burst (coils off)
    has ``|B|`` the earth field's magnitude ``earth_field_t`` in a clean room:
    ``x_quiet = ((|B| - earth_field_t) / quality_quiet_sigma_t)^2`` (0 when the sigma is 0 or
    no sample is there).

``quality = round(255 e0 / (e0 + e))`` with ``e0 = quality_error_scale_m`` (128 at ``e = e0``):
255 for a perfectly determined still pose, falling strictly with each part; 0 for a non-finite
input. The motion term's Jacobian ``H`` costs no field evaluation (the tick's work budget counts
those): its orientation columns are ``[h_j]x`` with the measured signals for ``h_j``, its
position columns the dipole gradient (eq 10), which is an algebraic function of the field and
the position (:meth:`PoseQuality._jacobian`). Against the exact loop that is a relative error of
``(a / r)^2`` (13 % at 15 cm from the thesis source's 5.5 cm coils, 2 % at 40 cm), within what
a motion known to one cycle allows. Allocation-free after ``__init__``: Python floats and
preallocated buffers.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import rotvec_from_matrix

__all__ = ["quality_from", "PoseQuality"]


def quality_from(var_trace_m2: float, x: float, scale_m: float, motion_m2: float = 0.0) -> int:
    """``round(255 e0 / (e0 + e))``, ``e = sqrt(var_trace max(1, x) + motion_m2)`` (module
    docstring); 0 if an input is not finite or a variance is negative."""
    if not (math.isfinite(x) and math.isfinite(var_trace_m2) and math.isfinite(motion_m2)) \
            or var_trace_m2 < 0.0 or motion_m2 < 0.0:
        return 0
    e = math.sqrt(var_trace_m2 * (x if x > 1.0 else 1.0) + motion_m2)
    q = int(255.0 * scale_m / (scale_m + e) + 0.5)
    return 255 if q > 255 else q


class PoseQuality:
    """Grades a solved pose (module docstring). ``n_coils``: the solver's coils;
    ``channels``: the sensor channels whose newest sample is the quiet field; ``coils``
    (``field.Coil``, optional): the source, for the motion within a pulsed burst
    (:meth:`grade_burst`); ``core`` (``coiltrack.firmware.core.Core``): on the compiled one
    :meth:`grade_burst` runs ``core/src/finish.c`` (``ct_grade_burst``, the same operations in the
    same order: the same quality, motion term and residual to the bit)."""

    def __init__(self, cfg, n_coils: int, channels=(), coils=None, core=_DEFAULT_CORE):
        self.scale = float(cfg.quality.quality_error_scale_m)
        self.earth = float(cfg.orientation.earth_field_t)
        self.quiet_sigma = float(cfg.quality.quality_quiet_sigma_t)
        self.dof = 3 * int(n_coils) - 6
        self._quiet_off = self.quiet_sigma <= 0.0 or self.earth <= 0.0      # quiet_term is 0
        self._rings = {ch.node: (ch.ring, ch.ring.bv) for ch in channels
                       if hasattr(ch, "ring")}
        self.last = {ch.node: 0 for ch in channels}     # the last quality per node (0 before any)
        self.motion_m2 = 0.0             # the last graded pose's |dp_motion|^2 (m^2)
        self.chi2_motion = 0.0           # and the residual its motion explains
        self._n = 0                      # coils of the motion term (0: none)
        if coils is not None and getattr(getattr(cfg, "ac", None), "excitation", "pulsed") == "pulsed" and len(coils) >= 2:
            n = len(coils)
            self._n = n
            self._c = [tuple(float(v) for v in c.center) for c in coils]
            self._scratch(n)
        # the motion is taken from the previous solution no older than two cycles
        self.max_gap_us = 2 * int(getattr(getattr(cfg, "timing", None), "cycle_us", 0))
        # per node: [have, t_us, px, py, pz, r00, r01, r02, r10, r11, r12, r20, r21, r22], one row
        # of _prev_rows each (the compiled grading reads and writes the same rows)
        self._row = {}
        for ch in channels:
            self._row.setdefault(ch.node, len(self._row))
        self._prev_rows = np.zeros((max(len(self._row), 1), 14))
        self._prev = {node: memoryview(self._prev_rows[k]) for node, k in self._row.items()}
        if self._n and core.ext is not None:
            self._bind_compiled(core.ext)
        elif core.ext is not None and n_coils >= 2:
            self._bind_chain_scratch(int(n_coils))

    def _bind_compiled(self, ext) -> None:
        """:meth:`grade_burst` on the compiled core (``ct_grade_burst`` through a
        ``BurstQuality`` bound to this grader's rows and scratch); the method is replaced on this
        instance, so no call tests the choice."""
        self._motion_out = np.zeros(2)
        self._mov = memoryview(self._motion_out)
        self._centers = np.array(self._c, dtype=float)
        self._bq = ext.BurstQuality(self._n, self.dof, self.scale, float(self.max_gap_us), self._centers,
                                    self._prev_rows, self._H, self._u, self._g, self._dx, self._d, self._xd,
                                    self._motion_out)
        self.grade_burst = self._grade_burst_compiled

    def _bind_chain_scratch(self, n: int) -> None:
        """Without the motion term (AC blocks, fewer than two coils' worth of source): the buffers a
        compiled report (:meth:`report_chain`) binds, its motion term off (``ct_grade_burst`` with no
        motion coils: :meth:`grade_burst`'s ``_n`` 0). :meth:`grade_burst` stays the Python."""
        self._motion_out = np.zeros(2)
        self._mov = memoryview(self._motion_out)
        self._centers = np.zeros((n, 3))
        self._scratch(n)
        self._chain_n = n

    def _scratch(self, n: int) -> None:
        """The motion term's scratch for ``n`` coils (``ct_grade_burst``'s ``H``, ``u``, ``g``, ``dx``,
        ``d``, ``xd``)."""
        self._H = memoryview(np.zeros(18 * n))
        self._u = memoryview(np.zeros(3 * n))
        self._g = memoryview(np.zeros(6))
        self._dx = memoryview(np.zeros(6))
        self._d = memoryview(np.zeros(n))
        self._xd = memoryview(np.zeros(6))

    def _grade_burst_compiled(self, node: int, t_us: int, cost: float, cov, p, R, S, sigma,
                              start, end, nis_per_dim: float = 0.0) -> int:
        """:meth:`grade_burst` in one compiled call (the arrays of another kind than the
        tracker's: by the Python)."""
        q = self._bq.grade(self._row.get(node, -1), t_us, cost, nis_per_dim, self.quiet_term(node), cov, p, R, S,
                           sigma, start, end)
        if q is None:
            return PoseQuality.grade_burst(self, node, t_us, cost, cov, p, R, S, sigma, start, end, nis_per_dim)
        mv = self._mov
        self.motion_m2 = mv[0]
        self.chi2_motion = mv[1]
        self.last[node] = q
        return q

    def report_chain(self, ext, node: int, sp, sR, scov, tp, tR, S, sigma, start, end, q, motion=None):
        """A compiled report of ``node``'s solved bursts (``ext.ReportChain``, ``core/src/report.c``)
        bound to the solver's results ``sp``, ``sR``, ``scov``, the tracked pose ``tp``, ``tR``, the
        channel's ``S`` and ``sigma``, the pulses' ``start`` and ``end``, the quaternion ``q`` (4,)
        and this grader's row of ``node`` and scratch; ``motion``: ``(w_last, velocity, out,
        burst_rms_s)`` of the reported covariance's motion term, or None. None when the grading is
        not compiled or ``node`` has no row (the Python grades)."""
        if getattr(self, "_motion_out", None) is None or node not in self._row:
            return None
        n = self._n if self._n else getattr(self, "_chain_n", 0)
        if self._n == 0 and type(self).grade_burst is not PoseQuality.grade_burst:
            return None                  # a grading the chain does not repeat
        wl, v, cov, rms = (None, None, None, 0.0) if motion is None else motion
        rv = None if self._quiet_off else self._rings.get(node)
        if rv is not None and (type(self).quiet_term is not PoseQuality.quiet_term or not hasattr(rv[0], "hc")):
            return None                  # a quiet term the chain does not repeat
        chain = ext.ReportChain(n, self.dof, self.scale, float(self.max_gap_us), self._row[node], self._centers,
                               self._prev_rows, self._H, self._u, self._g, self._dx, self._d, self._xd,
                               self._motion_out, sp, sR, scov, tp, tR, S, sigma, start, end, q, wl, v, cov,
                               float(rms), self._n)
        if rv is not None:               # the quiet term read by the chain (report: ct_report_quiet)
            chain.bind_quiet(rv[0].hc, rv[0].b, self.earth, self.quiet_sigma)
        return chain

    def grade_report(self, chain, node: int, t_us: int, cost: float, range_m: float, initialized: bool,
                     nis_per_dim: float = 0.0) -> int:
        """A solved burst's report through ``chain`` (:meth:`report_chain`; ``ct_report_solved``):
        -1 when the solution lies beyond ``range_m`` (nothing graded), else its quality as
        :meth:`grade_burst` gives it (kept in ``last[node]``, the motion in ``motion_m2`` and
        ``chi2_motion``)."""
        q = chain.report(t_us, cost, nis_per_dim, range_m, initialized)    # quiet_term(node) in the call
        if q >= 0:
            mv = self._mov
            self.motion_m2 = mv[0]
            self.chi2_motion = mv[1]
            self.last[node] = q
        return q

    def fit_term(self, cost: float) -> float:
        """``chi2 / dof`` (0 without residual freedom)."""
        return cost / self.dof if self.dof > 0 else 0.0

    def quiet_term(self, node: int) -> float:
        """``((|B| - earth_field_t) / sigma)^2`` of the newest sample of ``node`` (0 if unused)."""
        if self._quiet_off:
            return 0.0
        rv = self._rings.get(node)
        if rv is None:
            return 0.0
        p = rv[0].peek(0)                # -1: the ring is empty
        if p < 0:
            return 0.0
        p *= 3
        b = rv[1]
        m = math.sqrt(b[p] * b[p] + b[p + 1] * b[p + 1] + b[p + 2] * b[p + 2])
        z = (m - self.earth) / self.quiet_sigma
        return z * z

    def consistency(self, node: int, cost: float, nis_per_dim: float = 0.0) -> float:
        """``x = x_fit + x_nis + x_quiet`` (module docstring)."""
        return self.fit_term(cost) + nis_per_dim + self.quiet_term(node)

    def grade(self, node: int, cost: float, var_trace_m2: float, nis_per_dim: float = 0.0) -> int:
        """The quality of a pose of ``node`` without a motion term: the fit's ``cost``, the trace
        of its position covariance (m^2) and the filter's NIS per dimension (0: none); kept in
        ``last[node]``."""
        q = quality_from(var_trace_m2, self.consistency(node, cost, nis_per_dim), self.scale)
        self.last[node] = q
        return q

    def grade_burst(self, node: int, t_us: int, cost: float, cov, p, R, S, sigma,
                    start, end, nis_per_dim: float = 0.0) -> int:
        """The quality of the pose of ``node`` solved from one burst whose middle is ``t_us``:
        the fit's ``cost``, its covariance ``cov`` (6, 6; position, then orientation), position
        ``p`` (3,) and rotation ``R`` (3, 3, sensor to source), the burst's signals ``S`` (3, n,
        sensor frame, T) and their ``sigma`` (3, n), the pulses' ``start`` and ``end`` (n, master
        us). Adds
        the motion within the burst and takes the residual it explains out of the fit's
        (module docstring); kept in ``last[node]``."""
        var_trace = cov[0, 0] + cov[1, 1] + cov[2, 2]
        self.motion_m2 = self.chi2_motion = 0.0
        if self._n:
            self._motion(node, t_us, cov, p, R, S, sigma, start, end)
            self._remember(node, t_us, p, R)
        fit = cost - self.chi2_motion
        x = (fit / self.dof if self.dof > 0 and fit > 0.0 else 0.0) + nis_per_dim + self.quiet_term(node)
        q = quality_from(var_trace, x, self.scale, self.motion_m2)
        self.last[node] = q
        return q

    def _remember(self, node: int, t_us: int, p, R) -> None:
        st = self._prev.get(node)
        if st is None:
            return
        st[0] = 1.0
        st[1] = float(t_us)
        st[2], st[3], st[4] = p[0], p[1], p[2]
        for i in range(3):
            for j in range(3):
                st[5 + 3 * i + j] = R[i, j]

    def _jacobian(self, p, R, S) -> None:
        """``H_j = [R^T J_j, [h_j]x]`` (Schepers & Veltink eqs 9-11) into ``_H`` with ``h_j`` the
        measured column ``S[:, j]`` and ``J_j`` the dipole gradient (eq 10) written in the field
        itself: with ``B = R h_j`` (source frame), ``r = |p - c_j|``, ``n = (p - c_j) / r`` and
        ``b = B . n``, eq 8 gives ``c m = 1.5 b n - B`` and ``c (m . n) = b / 2``
        (``c = mu0 / (4 pi r^3)``), so ``J = (3 / r) (c m n^T + n c m^T + c (m . n) (I - 5 n n^T))``
        needs no field evaluation."""
        H = self._H
        for j in range(self._n):
            hx, hy, hz = S[0, j], S[1, j], S[2, j]
            bx = R[0, 0] * hx + R[0, 1] * hy + R[0, 2] * hz
            by = R[1, 0] * hx + R[1, 1] * hy + R[1, 2] * hz
            bz = R[2, 0] * hx + R[2, 1] * hy + R[2, 2] * hz
            cx, cy, cz = self._c[j]
            rx, ry, rz = p[0] - cx, p[1] - cy, p[2] - cz
            r = math.sqrt(rx * rx + ry * ry + rz * rz)
            if not r > 0.0:
                r = 1e-9
            nx, ny, nz = rx / r, ry / r, rz / r
            b = bx * nx + by * ny + bz * nz
            mx, my, mz = 1.5 * b * nx - bx, 1.5 * b * ny - by, 1.5 * b * nz - bz
            mr = 0.5 * b
            k = 3.0 / r
            # J (source frame) row a, column c; then row i of R^T J: sum_a R[a, i] J[a, c]
            j00 = k * (2.0 * mx * nx + mr - 5.0 * mr * nx * nx)
            j11 = k * (2.0 * my * ny + mr - 5.0 * mr * ny * ny)
            j22 = k * (2.0 * mz * nz + mr - 5.0 * mr * nz * nz)
            j01 = k * (mx * ny + nx * my - 5.0 * mr * nx * ny)
            j02 = k * (mx * nz + nx * mz - 5.0 * mr * nx * nz)
            j12 = k * (my * nz + ny * mz - 5.0 * mr * ny * nz)
            for i in range(3):
                a0, a1, a2 = R[0, i], R[1, i], R[2, i]
                o = 6 * (3 * j + i)
                H[o] = a0 * j00 + a1 * j01 + a2 * j02
                H[o + 1] = a0 * j01 + a1 * j11 + a2 * j12
                H[o + 2] = a0 * j02 + a1 * j12 + a2 * j22
            # [h]x
            o = 18 * j
            H[o + 3], H[o + 4], H[o + 5] = 0.0, -hz, hy
            H[o + 9], H[o + 10], H[o + 11] = hz, 0.0, -hx
            H[o + 15], H[o + 16], H[o + 17] = -hy, hx, 0.0

    def _motion(self, node: int, t_us: int, cov, p, R, S, sigma, start, end) -> None:
        """``motion_m2 = |dp_motion|^2`` and ``chi2_motion`` of this burst (module docstring);
        both stay 0 without a recent previous solution of ``node``."""
        st = self._prev.get(node)
        if st is None or st[0] == 0.0:
            return
        dt_us = t_us - st[1]
        if not 0.0 < dt_us <= self.max_gap_us:
            return
        inv = 1e6 / dt_us
        xd = self._xd
        xd[0] = (p[0] - st[2]) * inv
        xd[1] = (p[1] - st[3]) * inv
        xd[2] = (p[2] - st[4]) * inv
        # R_prev^T R (sensor frame): element (i, j) = sum_k R_prev[k, i] R[k, j]
        a00 = st[5] * R[0, 0] + st[8] * R[1, 0] + st[11] * R[2, 0]
        a01 = st[5] * R[0, 1] + st[8] * R[1, 1] + st[11] * R[2, 1]
        a02 = st[5] * R[0, 2] + st[8] * R[1, 2] + st[11] * R[2, 2]
        a10 = st[6] * R[0, 0] + st[9] * R[1, 0] + st[12] * R[2, 0]
        a11 = st[6] * R[0, 1] + st[9] * R[1, 1] + st[12] * R[2, 1]
        a12 = st[6] * R[0, 2] + st[9] * R[1, 2] + st[12] * R[2, 2]
        a20 = st[7] * R[0, 0] + st[10] * R[1, 0] + st[13] * R[2, 0]
        a21 = st[7] * R[0, 1] + st[10] * R[1, 1] + st[13] * R[2, 1]
        a22 = st[7] * R[0, 2] + st[10] * R[1, 2] + st[13] * R[2, 2]
        wx, wy, wz = rotvec_from_matrix(a00, a01, a02, a10, a11, a12, a20, a21, a22)
        xd[3], xd[4], xd[5] = wx * inv, wy * inv, wz * inv
        n = self._n
        d = self._d
        for j in range(n):
            d[j] = ((int(start[j]) + int(end[j])) * 0.5 - t_us) * 1e-6   # int(): no numpy int64 arithmetic
        H, u, g = self._H, self._u, self._g
        self._jacobian(p, R, S)
        # u = D H xdot; g = H^T W u
        for k in range(6):
            g[k] = 0.0
        for q in range(3 * n):
            o = 6 * q
            s = sigma[q % 3, q // 3]
            w = 1.0 / (s * s) if s > 0.0 else 0.0
            uq = d[q // 3] * (H[o] * xd[0] + H[o + 1] * xd[1] + H[o + 2] * xd[2]
                              + H[o + 3] * xd[3] + H[o + 4] * xd[4] + H[o + 5] * xd[5])
            u[q] = uq
            wu = w * uq
            for k in range(6):
                g[k] += H[o + k] * wu
        # dx = P g
        dx = self._dx
        for i in range(6):
            acc = 0.0
            for k in range(6):
                acc += cov[i, k] * g[k]
            dx[i] = acc
        self.motion_m2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]
        # the residual the motion leaves: u - H dx, weighted
        c2 = 0.0
        for q in range(3 * n):
            o = 6 * q
            s = sigma[q % 3, q // 3]
            if s > 0.0:
                r = u[q] - (H[o] * dx[0] + H[o + 1] * dx[1] + H[o + 2] * dx[2]
                            + H[o + 3] * dx[3] + H[o + 4] * dx[4] + H[o + 5] * dx[5])
                c2 += r * r / (s * s)
        self.chi2_motion = c2
        if not (math.isfinite(self.motion_m2) and math.isfinite(c2)):
            self.motion_m2 = self.chi2_motion = 0.0
