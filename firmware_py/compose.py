"""The one place the firmware's pipeline is composed from the configuration.

:func:`pipeline_choice` reads the configuration's choice of pipeline (``[ac] excitation``,
``[adaptive] actuation`` and ``single_coil_fusion``, ``[fusion] fusion``, ``[tight]
tight_fusion``) and :data:`TRACKERS` maps it to the builder of the actuate, measure and
track stages; :data:`SOLVERS` maps ``[pose] pose_solver`` to the pose solver the trackers of
bursts use. Nothing else chooses a component: the loop (:mod:`coiltrack.firmware.loop`) runs
what is built here, and no component tests a flag to behave as another.

Each stage is behind a ``typing.Protocol``: :class:`coiltrack.firmware.track.Tracker` (and
:class:`~coiltrack.firmware.track.BurstTracker`), :class:`coiltrack.firmware.actuate.Actuation`,
:class:`coiltrack.firmware.measure.Measurement`, :class:`coiltrack.firmware.pose.Solver`, and
the link :class:`coiltrack.firmware.port.Port`. Adding a tracker is a module that implements
the tracker's Protocol and one line in :data:`TRACKERS` (``docs/guide/extending.md``).

Everything is built here once, at start-up, and takes what it needs at construction (the
room's distortion map goes into every pose solver as it is built, :func:`solver_factory`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from coiltrack.firmware.actuate.ac import ACActuation
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.actuate.burst import BurstActuation
from coiltrack.firmware.measure.ac_blocks import ACBlockMeasurement
from coiltrack.firmware.measure.burst import BurstMeasurement
from coiltrack.firmware.pose import Solver
from coiltrack.firmware.track import Tracker
from coiltrack.firmware.track.ac import ACFusionTracker, ACMagneticTracker, StatusRouter
from coiltrack.firmware.track.burst_fusion import BurstFusionTracker
from coiltrack.firmware.track.magnetic import MagneticTracker
from coiltrack.firmware.track.single_coil_tracker import SingleCoilTracker
from coiltrack.firmware.track.tight_fusion import TightFusionTracker

__all__ = ["Parts", "Pipeline", "SOLVERS", "TRACKERS", "compose", "make_pose_solver", "pipeline_choice",
           "solver_factory"]


@dataclass(frozen=True)
class Pipeline:
    """The actuation, measurement and track stages (``step(now_us)`` callables) and the tracker
    of one configuration."""
    actuate: Callable[[int], None]
    measure: Callable[[int], None]
    track: Callable[[int], None]
    tracker: Tracker
    on_message: Callable | None = None     # messages the receiver does not route (AC_DRIVE_STATUS)
    #: when the sample that completes the open burst is expected (``Measurement.completing_sample_us``;
    #: None: the pipeline gives no such hint, its bursts are not aligned to)
    completing_sample_us: Callable[[], int] | None = None


@dataclass(frozen=True)
class Parts:
    """What every pipeline is built from: made once by :class:`coiltrack.firmware.loop.Firmware`.

    ``coils``: ``field.Coil`` (calibrated when the calibration says so); ``channels``: the
    sensor channels; ``schedule``: the one pulse schedule; ``closer``: the one window closer;
    ``distortion``: the room's map (``model.distortion.DistortionMap``) or None; ``core``: the
    numeric core (``coiltrack.firmware.core.Core``) every component binds its kernels from."""
    cfg: object
    coils: list
    channels: tuple
    schedule: object
    closer: object
    supervisor: object
    tx: object
    distortion: object = None
    core: object = _DEFAULT_CORE


# ------------------------------------------------------------------ pose solvers
def _lm(cfg, coils, gate_probability: float, core=_DEFAULT_CORE) -> Solver:
    from coiltrack.firmware.pose.solver import PoseSolver

    return PoseSolver(coils, cfg.source.field_model, gate_probability=gate_probability,
                      step_tol=cfg.pose.lm_step_tol, cost_tol=cfg.pose.lm_cost_tol, step_sigma=cfg.pose.lm_step_sigma, core=core)


def _raab(cfg, coils, gate_probability: float, core=_DEFAULT_CORE) -> Solver:
    from coiltrack.firmware.pose.raab import RaabTracker

    start = cfg.pose.raab_start_position
    return RaabTracker(coils, cfg.source.field_model, iters=cfg.pose.raab_iterations,
                       acquire_iters=cfg.pose.raab_acquire_iterations, gate_probability=gate_probability,
                       step_tol=cfg.pose.raab_step_tol, refresh=cfg.pose.raab_refresh, correction=cfg.pose.raab_correction,
                       start_position=start if any(v != 0.0 for v in start) else None,
                       start_euler=tuple(math.radians(v) for v in cfg.pose.raab_start_euler_deg),
                       hemisphere=cfg.source.hemisphere, step_sigma=cfg.pose.raab_step_sigma, core=core)


#: ``[pose] pose_solver`` -> the builder ``(cfg, coils, gate_probability, core) -> Solver``:
#: ``"lm"`` Kuipers' closed form and least squares (``pose.solver``); ``"raab"`` Raab et al. 1979
#: (``seeds/004_86267342cd7488ce.txt`` eqs 7-31, ``pose.raab``)
SOLVERS: dict[str, Callable] = {
    "lm": _lm,
    "raab": _raab,
}


def make_pose_solver(cfg, coils, gate_probability: float, distortion=None, core=_DEFAULT_CORE) -> Solver:
    """The solver ``cfg.pose.pose_solver`` for ``coils`` (``field.Coil``), with the signal model
    ``cfg.source.field_model``, a warm start's chi-square gate ``gate_probability`` and, when given, the
    room's distortion map in its signal model (``model.distortion``; a map of another number of
    coils is refused, ValueError), on the numeric core ``core``."""
    solver = SOLVERS[cfg.pose.pose_solver](cfg, coils, gate_probability, core)
    if distortion is not None:
        solver.signal.set_distortion(distortion)
    return solver


def solver_factory(cfg, coils, distortion=None, core=_DEFAULT_CORE) -> Callable[[float], Solver]:
    """``gate_probability -> Solver``: the configured solver, as :func:`make_pose_solver` builds
    it; a tracker that needs a second solver (the fused pipeline's motion-compensated
    re-solve) builds it with the same model and map."""
    def make(gate_probability: float) -> Solver:
        return make_pose_solver(cfg, coils, gate_probability, distortion, core)

    return make


# ------------------------------------------------------------------ pipelines
def pipeline_choice(cfg) -> str:
    """The key of :data:`TRACKERS` the configuration chooses."""
    if cfg.ac.excitation == "ac":
        return "ac-fusion" if cfg.fusion.fusion else "ac-magnetic"
    if cfg.adaptive.actuation == "adaptive":
        return "single-coil-adaptive"
    if cfg.adaptive.single_coil_fusion:
        return "single-coil-fixed"
    if cfg.tight.tight_fusion:
        return "tight-fusion"        # each pulse window a measurement at its own time ([tight])
    return "burst-fusion" if cfg.fusion.fusion else "magnetic"


def _bursts(kind: type) -> Callable[[Parts], Pipeline]:
    """The pipeline of ``kind``, a tracker of bursts of the fixed X, Y, Z cycle."""
    def build(p: Parts) -> Pipeline:
        cfg = p.cfg
        burst = BurstMeasurement(p.channels, p.schedule, p.closer, cfg.budget.windows_budget)
        t = kind(cfg, p.coils, p.channels, p.schedule, burst, p.supervisor, p.tx,
                 solver_factory(cfg, p.coils, p.distortion, p.core), core=p.core)
        act = BurstActuation(cfg, p.schedule, p.channels, t, p.core, burst)
        # burst.step drops a burst refused late first
        return Pipeline(act.step, burst.step, t.step, t, completing_sample_us=burst.completing_sample_us)

    return build


def _single_coil(mode: str) -> Callable[[Parts], Pipeline]:
    """Schepers & Veltink 2010: the tracker decides and measures its own pulses (``mode``:
    ``"adaptive"`` or the ``"fixed"`` cycle)."""
    def build(p: Parts) -> Pipeline:
        t = SingleCoilTracker(p.cfg, p.coils, p.channels, p.schedule, p.closer, p.supervisor, p.tx, mode,
                              distortion=p.distortion, core=p.core)
        return Pipeline(t.actuate, t.measure, t.track, t)

    return build


def _ac(kind: type) -> Callable[[Parts], Pipeline]:
    """AC excitation: the drive plan, demodulated blocks, ``kind`` (a burst tracker fed with them)."""
    def build(p: Parts) -> Pipeline:
        cfg = p.cfg
        act = ACActuation(cfg, p.tx)
        measure = ACBlockMeasurement(cfg, p.channels, p.schedule, act, core=p.core)
        t = kind(cfg, p.coils, p.channels, p.schedule, measure, act, p.supervisor, p.tx,
                 solver_factory(cfg, p.coils, p.distortion, p.core), core=p.core)
        return Pipeline(act.step, measure.step, t.step, t, StatusRouter(act, p.supervisor).on_message)

    return build


#: :func:`pipeline_choice` -> the builder of its pipeline from the :class:`Parts`
TRACKERS: dict[str, Callable[[Parts], Pipeline]] = {
    "magnetic": _bursts(MagneticTracker),                # magnetic poses only
    "burst-fusion": _bursts(BurstFusionTracker),         # thesis ch. 6
    "tight-fusion": _bursts(TightFusionTracker),         # each window at its own time ([tight])
    "single-coil-adaptive": _single_coil("adaptive"),    # Schepers & Veltink 2010
    "single-coil-fixed": _single_coil("fixed"),          # ... on the fixed cycle (single_coil_fusion)
    "ac-magnetic": _ac(ACMagneticTracker),               # AC blocks, magnetic poses
    "ac-fusion": _ac(ACFusionTracker),                   # AC blocks fused with the IMU
}


def compose(parts: Parts) -> Pipeline:
    """The pipeline the configuration chooses, built once."""
    return TRACKERS[pipeline_choice(parts.cfg)](parts)
