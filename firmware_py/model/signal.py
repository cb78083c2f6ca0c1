"""The one measurement model of the firmware: coil fields at the sensor and
their Jacobian with respect to the pose.

Source and sensor
    Coil ``j`` (``coiltrack.firmware.model.field.Coil``: centre ``c_j``, unit
    axis, radius ``a_j``, turns ``N_j``; any geometry, the coils need not be
    orthogonal or share a centre) carries the current ``I_j`` (A). Its flux
    density at the source-frame point ``p`` (m) is

        ``B_j(p) = R_j B_coil(R_j^T (p - c_j))``,  ``J_j = dB_j/dp = R_j J_coil R_j^T``

    (``R_j = Coil.rotation``, coil frame to source frame) with ``B_coil``
    the exact loop (Schepers & Veltink ``seeds/000_e46ec0e8bf7ea271.txt``
    eqs 6-7, elliptic integrals by the AGM, ``field.loop_point``) or the
    point dipole of moment ``N_j I_j pi a_j^2`` (eq 8 and the general form
    of eq 10, ``field.dipole_point``). Both are linear in ``I_j``.

Calibration (Raab ``seeds/004_86267342cd7488ce.txt``, "Source and Sensor
    Imperfections": the source matrix, one row per coil)
    A calibrated coil (``coiltrack.firmware.calibration.calibrated_coils``)
    carries its measured moment ``m_j = g_j u_j`` (direction ``u_j``, gain
    ``g_j`` relative to nominal) and winding centre ``c_j + o_j``: ``R_j``
    is built on ``u_j``, the centre moved by ``o_j`` and the field scale
    multiplied by ``g_j``, so the one product ``R_j B_coil(R_j^T (p - c_j))``
    above already applies the source matrix and the offset, and ``J_j``
    follows from the same rotation (the Jacobian stays consistent). The
    sensor's imperfections are removed from its samples on input
    (``coiltrack.firmware.receive``), never here.

Static distortion (``coiltrack.firmware.model.distortion``)
    With a room map (:meth:`SignalModel.set_distortion`, from the calibration
    file's ``[distortion]`` table) every evaluation adds ``I_j D_j(p)`` to
    ``B_j`` and ``I_j dD_j/dp`` to ``J_j`` (source frame), so the signals
    and the Jacobian below include it consistently.

Measurement (Schepers eq 5; thesis ``seeds/002_cd7f1fdb7fc67471.txt``
App. 5.A, eq 5.9 with the signal matrix ``S = R^T B``)
    ``h_j = R^T B_j(p)`` (T), the field of coil ``j`` in the sensor frame;
    ``R`` maps sensor-frame vectors to the source frame.

Jacobian (Schepers eqs 9-11)
    ``H_j = [R^T J_j(p), [h_j]x]`` (3 x 6) with respect to
    ``(dp, dtheta)``, where the orientation error is the sensor-frame
    rotation vector of ``R_true = R exp([dtheta]x)``: then
    ``h(R exp([dtheta]x)) = exp(-[dtheta]x) R^T B ~ h - [dtheta]x h
    = h + [h]x dtheta``, hence ``+[h]x`` (Schepers' eq 2 defines the error
    with the opposite sign, which flips eq 11).

Layout (all buffers flat and C-ordered, as numpy arrays ``(n, 3)`` and
``(n, 3, 6)``): ``h[3 j + i]`` is component ``i`` of coil ``j``; ``H`` row
``3 j + i`` holds the six derivatives ``(dp_x, dp_y, dp_z, dtheta_x,
dtheta_y, dtheta_z)`` at ``H[6 (3 j + i) + k]``. After any evaluation the
source-frame fields and gradients of the last point are in ``B`` (n, 3), T,
and ``J`` (n, 3, 3), T/m, ``J[j, r, c] = dB_j,r / dp_c``.

Cost accounting
    One coil's field (and gradient) at one point is one *field evaluation*;
    :attr:`SignalModel.evals` counts them (the caller may read it and set it
    back with :meth:`SignalModel.reset_evals`). This is the unit in which the
    pose solver's work per tick is bounded, independent of the machine.

Everything runs on Python floats and preallocated buffers: no numpy array is
created after ``__init__``.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.field import MU0, dipole_point, loop_point

__all__ = ["SignalModel", "FIELD_MODELS"]

FIELD_MODELS = ("exact", "dipole")


def _signed_permutation(r9):
    """``(i0, s0, i1, s1, i2, s2)`` when the row-major 3x3 ``r9`` has one entry of +-1 in each
    column ``k`` (in row ``i_k``, sign ``s_k``) and zeros elsewhere; else None."""
    out = []
    rows = set()
    for k in range(3):
        col = (r9[k], r9[3 + k], r9[6 + k])
        nz = [i for i in range(3) if col[i] != 0.0]
        if len(nz) != 1 or abs(col[nz[0]]) != 1.0:
            return None
        rows.add(nz[0])
        out += [nz[0], col[nz[0]]]
    return tuple(out) if len(rows) == 3 else None


class SignalModel:
    """Fields, signals and pose Jacobians of a set of coils.

    Parameters
    ----------
    coils : sequence of ``field.Coil``, length n >= 1
    model : {"exact", "dipole"}
    core : ``coiltrack.firmware.core.Core``
        The numeric core, chosen at composition (default: compiled where built).

    Attributes
    ----------
    n : int
    model : str
    B : ndarray (n, 3)      source-frame fields of the last point, T
    J : ndarray (n, 3, 3)   source-frame gradients of the last point, T/m
    Bv, Jv : memoryview     flat views of ``B`` and ``J`` (Python floats)
    evals : int             field evaluations so far (coils x points)
    """

    def __init__(self, coils, model: str = "exact", core=_DEFAULT_CORE):
        if model not in FIELD_MODELS:
            raise ValueError(f"model must be one of {FIELD_MODELS}, got {model!r}")
        n = len(coils)
        if n < 1:
            raise ValueError("coils: need at least one coil")
        self.n = n
        self.model = model
        self._exact = model == "exact"
        self._c = [tuple(float(v) for v in c.center) for c in coils]
        self._rot = [tuple(float(v) for v in c.rotation.reshape(9)) for c in coils]
        self._ax = [tuple(float(v) for v in c.axis) for c in coils]
        self._rad = [float(c.radius) for c in coils]
        # calibrated gain (Coil.gain, 1 when uncalibrated: coiltrack.firmware.calibration)
        self._spa = [c.gain * MU0 * c.turns / (2.0 * math.pi * c.radius) for c in coils]   # eq 6 scale per A, T
        self._mpa = [c.gain * c.turns * math.pi * c.radius * c.radius for c in coils]      # moment per A, A m^2
        self.B = np.zeros((n, 3))
        self.J = np.zeros((n, 3, 3))
        self.Bv = flat(self.B)
        self.Jv = flat(self.J)
        self.evals = 0
        #: the room's static distortion (``model.distortion.DistortionMap``) or None
        self.distortion = None
        # each coil's kernel, chosen once: a loop whose frame is a signed permutation of the
        # source frame's axes (coils along x, y, z) skips the two frame rotations' zero terms
        self._axes = [_signed_permutation(r) for r in self._rot]
        if self._exact:
            self._kernel = [self._loop if a is None else self._loop_axes for a in self._axes]
        else:
            self._kernel = [self._dipole] * n
        #: the numeric core this model runs, bound once here (``coiltrack.firmware.core``)
        self.core = "python"
        ext = core.ext
        if ext is not None and n <= ext.MAX_COILS:
            self._bind_compiled(ext)

    def _bind_compiled(self, ext) -> None:
        """Run :meth:`fields`, :meth:`predict` and :meth:`measure` on the compiled kernels
        (``core/src/signal.c``, the same operations in the same order as the methods below):
        the coils' geometry is packed once into ``_geom`` and the kernel bound to it and to
        ``B`` and ``J``; the methods are replaced on this instance, so no call tests the choice."""
        st = ext.COIL_STRIDE
        g = np.zeros((self.n, st))
        for j in range(self.n):
            row = g[j]
            if not self._exact:
                row[0] = ext.KIND_DIPOLE
            else:
                row[0] = ext.KIND_LOOP if self._axes[j] is None else ext.KIND_LOOP_AXES
            row[1:4] = self._c[j]
            row[4:13] = self._rot[j]
            row[13:16] = self._ax[j]
            row[16] = self._rad[j]
            row[17] = self._spa[j]
            row[18] = self._mpa[j]
            if self._axes[j] is not None:
                row[19:25] = self._axes[j]
        self._geom = g
        self._ck = ext.Signal(g, self.n, self.B, self.J)
        self.fields = self._fields_compiled
        self.predict = self._predict_compiled
        self.measure = self._measure_compiled
        self.core = "compiled"

    def _fields_compiled(self, px: float, py: float, pz: float, cur, jac: bool) -> None:
        self.evals += self.n
        self._ck.fields(px, py, pz, cur, jac)
        if self.distortion is not None:
            self.distortion.add(px, py, pz, cur, jac, self.Bv, self.Jv)

    def _predict_compiled(self, px: float, py: float, pz: float, R, cur, h) -> None:
        self.evals += self.n
        if self.distortion is None:
            self._ck.predict(px, py, pz, R, cur, h)
            return
        self._ck.fields(px, py, pz, cur, False)
        self.distortion.add(px, py, pz, cur, False, self.Bv, self.Jv)
        self._ck.project(R, h)

    def _measure_compiled(self, px: float, py: float, pz: float, R, cur, h, H) -> None:
        self.evals += self.n
        if self.distortion is None:
            self._ck.measure(px, py, pz, R, cur, h, H)
            return
        self._ck.fields(px, py, pz, cur, True)
        self.distortion.add(px, py, pz, cur, True, self.Bv, self.Jv)
        self._ck.project_jac(R, h, H)

    def set_distortion(self, dmap) -> None:
        """Add ``dmap``'s residual field ``I_j D_j(p)`` (and its gradient) to every evaluation
        (start-up; ``None`` removes it). ``model.distortion``."""
        if dmap is not None and dmap.n != self.n:
            raise ValueError(f"distortion map for {dmap.n} coils, the source has {self.n}")
        self.distortion = dmap

    def reset_evals(self) -> None:
        self.evals = 0

    def add_evals(self, count: int) -> None:
        """Count ``count`` coil-field evaluations a compiled kernel did with this model's geometry."""
        self.evals += count

    def charge(self, k: int) -> None:
        """Count ``k`` evaluations of every coil done by a compiled kernel bound to this model's
        geometry (``pose.solver``'s Levenberg-Marquardt): ``k n`` evaluations."""
        self.evals += k * self.n

    def moment_per_amp(self, j: int) -> tuple:
        """Dipole moment of coil ``j`` at 1 A, A m^2 (source frame)."""
        ax, ay, az = self._ax[j]
        m = self._mpa[j]
        return ax * m, ay * m, az * m

    # ------------------------------------------------------------ fields
    def fields(self, px: float, py: float, pz: float, cur, jac: bool) -> None:
        """``B_j(p)`` (and ``J_j(p)`` if ``jac``) of every coil into ``B`` /
        ``J`` for the currents ``cur`` (n floats, A); ``n`` evaluations."""
        self.evals += self.n
        kernel = self._kernel
        for j in range(self.n):
            kernel[j](j, px, py, pz, cur[j], jac)
        if self.distortion is not None:
            self.distortion.add(px, py, pz, cur, jac, self.Bv, self.Jv)

    def _loop(self, j, px, py, pz, current, jac):
        cx, cy, cz = self._c[j]
        dx, dy, dz = px - cx, py - cy, pz - cz
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._rot[j]
        # coil-frame point R_j^T (p - c_j)
        x = r00 * dx + r10 * dy + r20 * dz
        y = r01 * dx + r11 * dy + r21 * dz
        z = r02 * dx + r12 * dy + r22 * dz
        t = loop_point(x, y, z, self._rad[j], self._spa[j] * current, jac)
        bx, by, bz = t[0], t[1], t[2]
        Bv = self.Bv
        o = 3 * j
        Bv[o] = r00 * bx + r01 * by + r02 * bz
        Bv[o + 1] = r10 * bx + r11 * by + r12 * bz
        Bv[o + 2] = r20 * bx + r21 * by + r22 * bz
        if not jac:
            return
        jxx, jyy, jzz, jxy, jxz, jyz = t[3], t[4], t[5], t[6], t[7], t[8]
        # R_j Jc R_j^T, first T = R_j Jc
        t00 = r00 * jxx + r01 * jxy + r02 * jxz
        t01 = r00 * jxy + r01 * jyy + r02 * jyz
        t02 = r00 * jxz + r01 * jyz + r02 * jzz
        t10 = r10 * jxx + r11 * jxy + r12 * jxz
        t11 = r10 * jxy + r11 * jyy + r12 * jyz
        t12 = r10 * jxz + r11 * jyz + r12 * jzz
        t20 = r20 * jxx + r21 * jxy + r22 * jxz
        t21 = r20 * jxy + r21 * jyy + r22 * jyz
        t22 = r20 * jxz + r21 * jyz + r22 * jzz
        Jv = self.Jv
        o = 9 * j
        Jv[o] = t00 * r00 + t01 * r01 + t02 * r02
        Jv[o + 1] = t00 * r10 + t01 * r11 + t02 * r12
        Jv[o + 2] = t00 * r20 + t01 * r21 + t02 * r22
        Jv[o + 3] = t10 * r00 + t11 * r01 + t12 * r02
        Jv[o + 4] = t10 * r10 + t11 * r11 + t12 * r12
        Jv[o + 5] = t10 * r20 + t11 * r21 + t12 * r22
        Jv[o + 6] = t20 * r00 + t21 * r01 + t22 * r02
        Jv[o + 7] = t20 * r10 + t21 * r11 + t22 * r12
        Jv[o + 8] = t20 * r20 + t21 * r21 + t22 * r22

    def _loop_axes(self, j, px, py, pz, current, jac):
        """:meth:`_loop` for a coil whose ``R_j`` is a signed permutation: column ``k`` of
        ``R_j`` is ``s_k`` times the source axis ``i_k``, so ``(R_j^T d)_k = s_k d_{i_k}``,
        ``B_{i_k} = s_k b_k`` and ``J_{i_k, i_m} = s_k s_m Jc_{k m}``: the products of the general
        path without its terms that are zero (the same values, bit for bit, for finite input)."""
        cx, cy, cz = self._c[j]
        d = (px - cx, py - cy, pz - cz)
        i0, s0, i1, s1, i2, s2 = self._axes[j]
        t = loop_point(s0 * d[i0], s1 * d[i1], s2 * d[i2], self._rad[j], self._spa[j] * current, jac)
        Bv = self.Bv
        o = 3 * j
        Bv[o + i0] = s0 * t[0]
        Bv[o + i1] = s1 * t[1]
        Bv[o + i2] = s2 * t[2]
        if not jac:
            return
        Jv = self.Jv
        o = 9 * j
        r0, r1, r2 = o + 3 * i0, o + 3 * i1, o + 3 * i2
        Jv[r0 + i0] = t[3]
        Jv[r1 + i1] = t[4]
        Jv[r2 + i2] = t[5]
        Jv[r0 + i1] = Jv[r1 + i0] = s0 * s1 * t[6]
        Jv[r0 + i2] = Jv[r2 + i0] = s0 * s2 * t[7]
        Jv[r1 + i2] = Jv[r2 + i1] = s1 * s2 * t[8]

    def _dipole(self, j, px, py, pz, current, jac):
        cx, cy, cz = self._c[j]
        ax, ay, az = self._ax[j]
        m = self._mpa[j] * current
        t = dipole_point(px - cx, py - cy, pz - cz, ax * m, ay * m, az * m, jac)
        Bv = self.Bv
        o = 3 * j
        Bv[o], Bv[o + 1], Bv[o + 2] = t[0], t[1], t[2]
        if not jac:
            return
        Jv = self.Jv
        o = 9 * j
        Jv[o], Jv[o + 4], Jv[o + 8] = t[3], t[4], t[5]
        Jv[o + 1] = Jv[o + 3] = t[6]
        Jv[o + 2] = Jv[o + 6] = t[7]
        Jv[o + 5] = Jv[o + 7] = t[8]

    # ------------------------------------------------------- measurement
    def predict(self, px: float, py: float, pz: float, R, cur, h) -> None:
        """Signals ``h[3 j + i] = (R^T B_j(p))_i`` (T) without the Jacobian.

        ``R`` (3, 3) indexable ``R[r, c]`` (a numpy array or a 2-D
        memoryview), sensor to source; ``cur`` n currents, A; ``n`` evaluations.
        """
        self.fields(px, py, pz, cur, False)
        Bv = self.Bv
        r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
        r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
        r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
        for j in range(self.n):
            o = 3 * j
            bx, by, bz = Bv[o], Bv[o + 1], Bv[o + 2]
            h[o] = r00 * bx + r10 * by + r20 * bz
            h[o + 1] = r01 * bx + r11 * by + r21 * bz
            h[o + 2] = r02 * bx + r12 * by + r22 * bz

    def measure(self, px: float, py: float, pz: float, R, cur, h, H) -> None:
        """Signals ``h`` (3n) and Jacobian ``H`` (3n x 6) at the pose (p, R).

        ``h_j = R^T B_j(p)`` (Schepers eq 5), ``H_j = [R^T J_j(p), [h_j]x]``
        (eqs 9-11, orientation error ``R_true = R exp([dtheta]x)``). Layout
        in the module docstring; ``R`` and ``cur`` as in :meth:`predict`;
        ``n`` evaluations.
        """
        self.fields(px, py, pz, cur, True)
        Bv = self.Bv
        Jv = self.Jv
        r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
        r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
        r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
        for j in range(self.n):
            o = 3 * j
            bx, by, bz = Bv[o], Bv[o + 1], Bv[o + 2]
            hx = r00 * bx + r10 * by + r20 * bz
            hy = r01 * bx + r11 * by + r21 * bz
            hz = r02 * bx + r12 * by + r22 * bz
            h[o], h[o + 1], h[o + 2] = hx, hy, hz
            g = 9 * j
            j00, j01, j02 = Jv[g], Jv[g + 1], Jv[g + 2]
            j10, j11, j12 = Jv[g + 3], Jv[g + 4], Jv[g + 5]
            j20, j21, j22 = Jv[g + 6], Jv[g + 7], Jv[g + 8]
            # eq 9: rows of R^T J_j (row i uses column i of R)
            q = 18 * j
            H[q] = r00 * j00 + r10 * j10 + r20 * j20
            H[q + 1] = r00 * j01 + r10 * j11 + r20 * j21
            H[q + 2] = r00 * j02 + r10 * j12 + r20 * j22
            H[q + 6] = r01 * j00 + r11 * j10 + r21 * j20
            H[q + 7] = r01 * j01 + r11 * j11 + r21 * j21
            H[q + 8] = r01 * j02 + r11 * j12 + r21 * j22
            H[q + 12] = r02 * j00 + r12 * j10 + r22 * j20
            H[q + 13] = r02 * j01 + r12 * j11 + r22 * j21
            H[q + 14] = r02 * j02 + r12 * j12 + r22 * j22
            # eq 11 (sign for R_true = R exp([dtheta]x)): [h_j]x
            H[q + 3], H[q + 4], H[q + 5] = 0.0, -hz, hy
            H[q + 9], H[q + 10], H[q + 11] = hz, 0.0, -hx
            H[q + 15], H[q + 16], H[q + 17] = -hy, hx, 0.0
