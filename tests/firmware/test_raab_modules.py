"""The pieces of Raab's tracker (``firmware_py/pose/raab*.py``; Raab et al. 1979,
``seeds/004_86267342cd7488ce.txt``) and the seams between them, against references
that share nothing with them.

* ``model.field.dipole_polar``, Raab's dipole (eq 5) in direction and range: against
  the closed form ``B = mu0 / (4 pi) (3 (m . r) r / r^5 - m / r^3)`` written here in
  numpy and its gradient against central differences of magpylib's dipole core, and
  against the field module's point kernel ``dipole_point`` at ``p = rho u``.
* ``raab_update.detect``: on couplings of the dipole written out here, zero at the
  truth and the known error to first order (eqs 7, 11, 21-26).
* The correction is a component chosen at construction (``raab_correction``):
  ``NoCorrection`` passes the signals through; ``LoopCorrection`` removes exactly
  what its cache holds.
* No module of the tracker, the signal model or the measurement writes another
  object's state (parsed with ``ast``: no ``a.b.c = ...``, no ``other.x = ...``).
"""
from __future__ import annotations

import ast
import math
from pathlib import Path

import magpylib
import numpy as np
import pytest

from coiltrack.firmware.model.field import MU0, dipole_point, dipole_polar, orthogonal_source
from coiltrack.firmware.pose.raab import RaabTracker
from coiltrack.firmware.pose.raab_correction import LoopCorrection, NoCorrection
from coiltrack.firmware.pose.raab_update import detect, dcm

ROOT = Path(__file__).resolve().parents[2]
COILS = orthogonal_source(0.055, 50)


def _closed_form(p, m):
    r = np.linalg.norm(p)
    return MU0 / (4 * math.pi) * (3 * (m @ p) * p / r ** 5 - m / r ** 3)


def _magpy_dipole(p, m):
    return MU0 * magpylib.core.dipole_Hfield(np.atleast_2d(p), np.atleast_2d(m))[0]


def _full(t):
    bx, by, bz, jxx, jyy, jzz, jxy, jxz, jyz = t
    return np.array([bx, by, bz]), np.array([[jxx, jxy, jxz], [jxy, jyy, jyz], [jxz, jyz, jzz]])


def _points(rng, k):
    for _ in range(k):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        yield u, rng.uniform(0.05, 2.0), rng.normal(size=3) * rng.uniform(0.01, 1.0)


def test_dipole_polar_is_the_dipole_field_and_gradient():
    """Field within 1e-13 of the numpy closed form, gradient within 1e-7 of
    magpylib's central differences (h = 1e-6 rho), and both within 1e-14 of the
    point kernel at ``p = rho u``. Catches a factor (mu0 / 2 pi for mu0 / 4 pi),
    a sign, a swapped moment component, a wrong range power in the gradient
    (``rho^-4``) or the gradient's 15 (m.u) u u^T term."""
    rng = np.random.default_rng(31)
    for u, rho, m in _points(rng, 60):
        p = rho * u
        B, J = _full(dipole_polar(u[0], u[1], u[2], rho, m[0], m[1], m[2], True))
        ref = _closed_form(p, m)
        assert np.linalg.norm(B - ref) <= 1e-13 * np.linalg.norm(ref)
        h = 1e-6 * rho
        Jref = np.stack([(_magpy_dipole(p + h * e, m) - _magpy_dipole(p - h * e, m)) / (2 * h) for e in np.eye(3)],
                        axis=1)
        assert np.linalg.norm(J - Jref) <= 1e-7 * np.linalg.norm(Jref)
        Bp, Jp = _full(dipole_point(p[0], p[1], p[2], m[0], m[1], m[2], True))
        assert np.linalg.norm(B - Bp) <= 1e-14 * np.linalg.norm(Bp)
        assert np.linalg.norm(J - Jp) <= 1e-14 * np.linalg.norm(Jp)
        assert dipole_polar(u[0], u[1], u[2], rho, m[0], m[1], m[2], False) == tuple(B)


def _dipole_coupling(alpha, beta, rho, psi, theta, phi):
    """``F = A [B(e_x) B(e_y) B(e_z)]`` of unit moments along the source axes at Raab's
    coordinates, the fields from the closed form above (``A = T_phi T_theta T_psi``)."""
    u = np.array([math.cos(beta) * math.cos(alpha), math.cos(beta) * math.sin(alpha), -math.sin(beta)])
    Bs = np.stack([_closed_form(rho * u, e) for e in np.eye(3)], axis=1)
    A = np.array(dcm(psi, theta, phi)).reshape(3, 3)
    return A @ Bs


@pytest.mark.parametrize("k,delta", [(0, 2e-4), (1, -3e-4), (2, 1e-4 * 0.3), (3, 2e-4), (4, -2e-4), (5, 3e-4)])
def test_detect_finds_a_small_error_of_each_coordinate(k, delta):
    """At the truth the detected errors vanish (1e-12); with the estimate off
    by ``delta`` in one coordinate (alpha, beta, rho, psi, theta, phi at beta =
    theta = 0 and psi = alpha, where the tracking frame's error angles are the
    coordinates' own, eqs 27-31) the
    detection returns ``delta`` for it to first order (``2 |delta|^2``) and
    nothing else. Catches a sign or factor in eqs 22-26, the range of eq 21,
    or the post-sensing rotation applied on the wrong side."""
    true = [0.4, 0.0, 0.3, 0.4, 0.0, 0.2]
    F = _dipole_coupling(*true).reshape(9)
    R = np.array(dcm(*true[3:])).reshape(3, 3).T
    kf = np.linalg.norm(F) / math.sqrt(1.5)
    d = detect(true, R, F, kf)
    assert max(abs(v) for v in d) < 1e-12
    est = list(true)
    est[k] -= delta
    R = np.array(dcm(*est[3:])).reshape(3, 3).T
    d = detect(est, R, F, kf)
    # detect orders (alpha, beta, rho, psi, theta, phi); the update adds d
    want = [0.0] * 6
    want[k] = delta
    scale = est[2] if k == 2 else 1.0
    for got, w in zip(d, want):
        assert abs(got - w) <= 2.0 * (delta / scale) ** 2 * scale + 1e-12


def test_the_correction_is_a_component_chosen_at_construction():
    """``correction=False`` gives ``NoCorrection`` (the signals pass unchanged:
    Raab's detection of the measurement itself), the default ``LoopCorrection``,
    which subtracts ``R^T (b_j + G_j dp) I_j`` of its cache. Catches a component
    that corrects when told not to, or a correction not scaled by the current."""
    assert isinstance(RaabTracker(COILS, "exact", correction=False).corrector, NoCorrection)
    assert isinstance(RaabTracker(COILS, "exact").corrector, LoopCorrection)
    rng = np.random.default_rng(32)
    S = rng.normal(size=9)
    Sc = np.zeros(9)
    R = np.eye(3)[[1, 2, 0]]
    cur = np.array([1.5, 1.4, 1.6])
    NoCorrection().correct(S, Sc, 3, (0.2, 0.1, 0.0), [0.2, 0.1, 0.0], R, 0.22, cur)
    assert np.array_equal(Sc, S)
    lc = LoopCorrection(3)
    b = rng.normal(size=9)
    for i in range(9):
        lc.b[i] = b[i]
    lc.correct(S, Sc, 3, (0.2, 0.1, 0.0), [0.2, 0.1, 0.0], R, 0.22, cur)     # at p_m: G does not enter
    want = S.reshape(3, 3) - (R.T @ (b.reshape(3, 3).T * cur)).T
    assert np.allclose(Sc.reshape(3, 3), want, rtol=0, atol=1e-15)


#: the modules of the tracker, the signal model, the measurement and the reference solve
_OWN = ["firmware_py/pose/raab.py", "firmware_py/pose/raab_update.py", "firmware_py/pose/raab_correction.py",
        "firmware_py/pose/raab_covariance.py", "firmware_py/pose/reference.py", "firmware_py/pose/acquire.py",
        "firmware_py/model/field.py", "firmware_py/model/signal.py", "firmware_py/measure/demod.py",
        "firmware_py/measure/ac_blocks.py"]


def _foreign_writes(tree):
    """Assignments to ``a.b.c`` (another object's attribute) or to ``other.x`` with
    ``other`` not ``self`` (a module-level name, an argument)."""
    bad = []
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        stack = list(targets)
        while stack:
            t = stack.pop()
            if isinstance(t, (ast.Tuple, ast.List)):
                stack.extend(t.elts)
            elif isinstance(t, ast.Attribute):
                if not (isinstance(t.value, ast.Name) and t.value.id == "self"):
                    bad.append(f"line {t.lineno}: {ast.unparse(t)}")
    return bad


@pytest.mark.parametrize("path", _OWN)
def test_no_object_writes_another_objects_state(path):
    """Each writes only its own attributes (``self.x = ...``); another's state is
    changed by a method of its owner or given at construction."""
    tree = ast.parse((ROOT / path).read_text())
    assert _foreign_writes(tree) == []


def test_the_foreign_write_check_finds_one():
    """The check above is not vacuous: it reports ``self.tx.now_us = t`` and ``ins.ori.gate = g``."""
    tree = ast.parse("class A:\n    def f(self, ins, t, g):\n        self.tx.now_us = t\n        ins.ori.gate = g\n"
                     "        self.ok = True\n")
    assert len(_foreign_writes(tree)) == 2
