"""The one strapdown integration and inertial error transition of the firmware.

Both inertial filters, the magnetic-inertial complementary filter
(``magnetic_inertial.FusionFilter``, thesis ``002_cd7f1fdb7fc67471.txt``
ch. 6) and the single-coil EKF (``single_coil.SchepersEKF``, Schepers &
Veltink 2010 sec. 2.1 with the ch. 6 error model), propagate the same
inertial navigation state with these routines; they differ only in where the
orientation error lives (navigation frame or sensor frame) and in their
process noise.

Nominal state (``R`` sensor to navigation frame, specific force ``f`` and
rate ``w`` in the sensor frame, offsets removed; ``f_ref`` the specific force
of the navigation frame's origin: ``-g`` for a frame fixed on the earth, the
source's specific force for a moving source, eq 6.8)::

    R <- R exp([w T]x)                                   (eqs 2.27, 6.1)
    a  = R f - f_ref                                     (eqs 6.2, 6.8)
    v <- v + T (a0 + a1) / 2                             (eq 6.3)
    p <- p + T v + T^2 (a0 / 3 + a1 / 6)                 (eq 6.4)

(:meth:`Strapdown.rotate`, :func:`to_nav`, :func:`integrate_pv`; the
position and velocity steps are exact for an acceleration linear in time from
``a0`` to ``a1``; a constant one is ``a0 = a1``).

Error transition over ``T`` (``true = estimate + error``; state rows
``POS, VEL, ORI, ACC, GYR`` of ``layout``, the same indices in every
inertial filter), first order in ``T``, eq 6.17:

* :func:`transition_static`: ``POS-VEL = T I`` (eq 6.10) and the sensor
  error decays ``ACC-ACC = k_a I``, ``GYR-GYR = k_g I`` (first-order Markov,
  eqs 6.13-6.14; ``k = 1`` for a random walk);
* :func:`transition_nav`, orientation error in the navigation frame
  (``R_true = exp([ori]x) R``)::

      VEL-ORI = -T [R f x]   VEL-ACC = -T R   ORI-GYR = -T R   ORI-ORI = I

* :func:`transition_sensor`, orientation error in the sensor frame
  (``R_true = R exp([ori]x)``), with the ``T^2 / 2`` terms of the position::

      POS-ORI = -T^2/2 R [f x]   POS-ACC = -T^2/2 R
      VEL-ORI = -T R [f x]       VEL-ACC = -T R
      ORI-ORI = exp(-[w T]x)     ORI-GYR = -T I

Matrices are indexed ``M[i, j]`` (memoryviews of C-contiguous float64
arrays in the filters, for speed); nothing here creates an array.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, POS, VEL
from coiltrack.firmware.linalg import exp_rotvec

_P, _V, _O, _A, _G = POS.start, VEL.start, ORI.start, ACC.start, GYR.start


class Strapdown:
    """Scratch of the attitude step (two 3x3 buffers, allocated once)."""

    def __init__(self, core=_DEFAULT_CORE):
        self.E = np.eye(3)
        self.T = np.eye(3)
        self.Ev = memoryview(self.E)
        #: the numeric core of :meth:`rotate`, bound once here (``coiltrack.firmware.core``:
        #: ``core/src/strapdown.c`` ``ct_strapdown_rotate``, the same Rodrigues and a 3x3 product
        #: equal to the BLAS one to rounding; ``E`` is then not written)
        self.core = "python"
        ext = core.ext
        if ext is not None:
            self.rotate = ext.strapdown_rotate
            self.core = "compiled"

    def rotate(self, R, ux: float, uy: float, uz: float) -> None:
        """``R <- R exp([u]x)`` (``R`` a (3, 3) array; ``u = w T``, eqs 2.27, 6.1)."""
        exp_rotvec(ux, uy, uz, self.Ev)
        np.matmul(R, self.E, out=self.T)
        np.copyto(R, self.T)


def to_nav(R, x: float, y: float, z: float):
    """``R (x, y, z)``: a sensor-frame vector in the navigation frame."""
    return (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z,
            R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
            R[2, 0] * x + R[2, 1] * y + R[2, 2] * z)


def integrate_pv(p, v, dt: float, a0x: float, a0y: float, a0z: float,
                 a1x: float, a1y: float, a1z: float) -> None:
    """Position and velocity over ``dt`` with the acceleration going linearly
    from ``a0`` to ``a1`` (eqs 6.3-6.4; ``a = R f - f_ref``)."""
    c0 = dt * dt / 3.0
    c1 = dt * dt / 6.0
    p[0] += v[0] * dt + c0 * a0x + c1 * a1x
    p[1] += v[1] * dt + c0 * a0y + c1 * a1y
    p[2] += v[2] * dt + c0 * a0z + c1 * a1z
    h = 0.5 * dt
    v[0] += h * (a0x + a1x)
    v[1] += h * (a0y + a1y)
    v[2] += h * (a0z + a1z)


def transition_static(A, dt: float, ka: float, kg: float) -> None:
    """``POS-VEL = dt I`` (eq 6.10), ``ACC-ACC = ka I``, ``GYR-GYR = kg I`` (eqs 6.13-6.14)."""
    for i in range(3):
        A[_P + i, _V + i] = dt
        A[_A + i, _A + i] = ka
        A[_G + i, _G + i] = kg


def _put(A, r0: int, c0: int, s: float, R) -> None:
    """``A[r0:r0+3, c0:c0+3] = s R``."""
    for i in range(3):
        A[r0 + i, c0], A[r0 + i, c0 + 1], A[r0 + i, c0 + 2] = s * R[i, 0], s * R[i, 1], s * R[i, 2]


def transition_nav(A, dt: float, R, gx: float, gy: float, gz: float) -> None:
    """Blocks of eq 6.17 for a navigation-frame orientation error; ``g = R f``
    (the specific force in the navigation frame, mean over the step)."""
    # VEL-ORI: -dt [g x]
    A[_V, _O + 1] = dt * gz
    A[_V, _O + 2] = -dt * gy
    A[_V + 1, _O] = -dt * gz
    A[_V + 1, _O + 2] = dt * gx
    A[_V + 2, _O] = dt * gy
    A[_V + 2, _O + 1] = -dt * gx
    # VEL-ACC and ORI-GYR: the same -dt R, computed once
    m = -dt
    for i in range(3):
        a0, a1, a2 = m * R[i, 0], m * R[i, 1], m * R[i, 2]
        A[_V + i, _A], A[_V + i, _A + 1], A[_V + i, _A + 2] = a0, a1, a2
        A[_O + i, _G], A[_O + i, _G + 1], A[_O + i, _G + 2] = a0, a1, a2


def transition_sensor(A, dt: float, R, fx: float, fy: float, fz: float,
                      wx: float, wy: float, wz: float, sd: Strapdown) -> None:
    """Blocks of eq 6.17 for a sensor-frame orientation error, with the
    ``dt^2 / 2`` position terms (``sd``: scratch for ``exp(-[w dt]x)``)."""
    h2 = -0.5 * dt * dt
    for i in range(3):
        r0, r1, r2 = R[i, 0], R[i, 1], R[i, 2]
        # row i of R [f]x is (row i of R) x f
        m0 = r1 * fz - r2 * fy
        m1 = r2 * fx - r0 * fz
        m2 = r0 * fy - r1 * fx
        A[_P + i, _O], A[_P + i, _O + 1], A[_P + i, _O + 2] = h2 * m0, h2 * m1, h2 * m2
        A[_V + i, _O], A[_V + i, _O + 1], A[_V + i, _O + 2] = -dt * m0, -dt * m1, -dt * m2
        A[_O + i, _G + i] = -dt
    _put(A, _P, _A, h2, R)
    _put(A, _V, _A, -dt, R)
    exp_rotvec(-wx * dt, -wy * dt, -wz * dt, sd.Ev)
    _put(A, _O, _O, 1.0, sd.Ev)
