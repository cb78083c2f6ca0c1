"""The single-coil window update's arithmetic around the one-call EKF update, reference and
compiled (``track.single_coil_tracker.SingleCoilTracker._update``).

Before the update (:func:`window_prior`): whether the NIS tests the linearised model (the prior's
largest position variance small against the squared range, Schepers & Veltink 2010,
``seeds/000_e46ec0e8bf7ea271.txt`` sec. 3.2) and the predicted field's relative error (the field
model's and the current's). After it (:func:`window_after`): the pose quality's consistency term
(``track.quality.PoseQuality.consistency`` with no fit term: the update's NIS per dimension and the
quiet field's) and, where the model is linear, the NIS monitor's record (``NisMonitor.add``,
``add_used``; sec. 3.3).

On the compiled core each sensor has an ``ext.ScUpdateCore`` (:func:`update_core`; ``ct_scw_prior``,
``ct_scw_after`` in ``core/src/sc_window.c``) bound once to its filter's covariance and positions,
its monitor's arrays and its magnetometer ring: the same operations in the same order, so the
same bits, in one call before and one after the update. Where the sensor's filter, its update and
the tracker's shared baselines run compiled as well, :func:`window_update` binds the whole window
update (the prior, the channel's variance, ``SchepersEKF.update_pulse`` with its bookkeeping, the
after-steps) to one ``ext.ScWindowUpdate`` (``core/py_sc_close.c``): the same kernels in the same
order.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.shared_baseline import CompiledSharedBaselines
from coiltrack.firmware.estimate.single_coil import ORI, POS, SchepersEKF
from coiltrack.firmware.track.quality import PoseQuality
from coiltrack.firmware.track.single_coil_nis import CompiledNisMonitor

__all__ = ["window_prior", "window_after", "update_core", "window_update"]


def window_prior(P, nP: int, p, cp, k: int, lin2: float, rel2: float, tol_a: float,
                 current: float) -> tuple[bool, float]:
    """``(linear, rel)``: ``P`` the filter's covariance, flat (``nP`` x ``nP``); the update
    linearises at clone ``k``'s position (``cp[k, :]``) or, ``k = -1``, the state's (``p``);
    ``linear``: the largest prior position variance below ``lin2 |position|^2``; ``rel``: the
    predicted field's relative error, ``sqrt(rel2 + (tol_a / |current|)^2)`` (``|current|`` at
    least 1e-6 A)."""
    d = nP + 1
    b = POS.start * d
    sp2 = max(P[b], P[b + d], P[b + 2 * d])
    if k >= 0:
        x, y, z = cp[k, 0], cp[k, 1], cp[k, 2]
    else:
        x, y, z = p[0], p[1], p[2]
    r2 = x * x + y * y + z * z
    linear = sp2 < lin2 * r2
    rc = tol_a / max(abs(current), 1e-6)
    return linear, math.sqrt(rel2 + rc * rc)


def window_after(quality, node: int, mon, nis_nominal: float, nis: float, linear: bool) -> float:
    """The consistency term of ``node``'s pose after an update whose NIS is ``nis`` (returned);
    when ``linear``, the monitor ``mon`` records the nominal and the used NIS."""
    x = quality.consistency(node, 0.0, nis / 3.0)
    if linear:
        mon.add(nis_nominal)
        mon.add_used(nis)
    return x


def update_core(ext, s, quality, lin2: float, rel2: float, tol_a: float):
    """``(ScUpdateCore, w)`` for the sensor ``s`` (``single_coil_sensor.SensorTrack``), or None
    where the compiled pair would not repeat the reference: no extension, a monitor or a quality
    whose steps are not the reference's, a magnetometer ring without its compiled head and count.
    ``w``: a view of the float64 (1,) the core writes the linearisation flag to."""
    mon, ekf = s.monitor, s.ekf
    if ext is None or not isinstance(mon, CompiledNisMonitor) or type(quality).consistency is not PoseQuality.consistency \
            or type(quality).fit_term is not PoseQuality.fit_term or type(quality).quiet_term is not PoseQuality.quiet_term:
        return None
    quiet = quality.quiet_sigma > 0.0 and quality.earth > 0.0 and hasattr(s.track, "ring")
    if quiet and not hasattr(s.track.ring, "hc"):
        return None
    if not (ekf.P.flags.c_contiguous and ekf.clone_p.flags.c_contiguous and ekf.p.flags.c_contiguous):
        return None
    w = np.zeros(1)
    uc = ext.ScUpdateCore(ekf.P, ekf.P.shape[1], POS.start, ekf.p, ekf.clone_p, mon._buf, mon._bound, mon._st,
                          mon.window, mon.min_count, float(mon.dof), mon.min_mean, mon.max_scale, mon.excess_gate,
                          mon._alpha, lin2, rel2, tol_a, w)
    if quiet:
        uc.bind_quiet(s.track.ring.hc, s.track.ring.b, quality.earth, quality.quiet_sigma)
    return uc, memoryview(w)


def window_update(ext, s, uc, sharing, model):
    """``(ScWindowUpdate, out)`` for the sensor ``s``: its window update (``SingleCoilTracker._update``
    from ``window_prior`` to ``window_after``) in one call, or None where that call would not repeat
    the reference: no ``uc`` (:func:`update_core`), shared baselines without their compiled channel
    variance (``CompiledSharedBaselines`` with ``s``'s channel bound), a filter that is not the plain
    ``SchepersEKF`` on its compiled kernels (a coil-gain filter, the Python dynamics), an update
    not on its one-call run or whose run ``model`` cannot be bound to. ``out``: a view of the float64
    (``ext.WU_NOUT``,) the call writes the consistency term, the linear flag and the model's
    evaluations to. ``run(k, coil, current)`` returns the update's flags, -1 (nothing done) for a
    clone not taken yet (the reference's ``update_pulse`` takes it)."""
    ekf = s.ekf
    if uc is None or ext is None or type(ekf) is not SchepersEKF or getattr(ekf, "_ck", None) is None:
        return None
    u = ekf._coil_update
    if getattr(u, "_run_fused", None) is None or u.run != u._run_fused or u._run_model is not model and not (
            u._run_model is None and u._bind_run(model)):
        return None
    if not isinstance(sharing, CompiledSharedBaselines) or not s.index < sharing._bound:
        return None
    sb = sharing._ck
    out = np.zeros(ext.WU_NOUT)
    upd = u.upd
    wk = ext.ScWindowUpdate(uc[0], sb, s.index, u._ck, ekf._ck, ekf.P, s.track.amp, POS.start, ORI.start, upd.gate,
                            u.iterations, upd.kst, upd._nis, ekf.ust, ekf.ucnt, out)
    return wk, memoryview(out)
