"""The magnetic-only tracker: one 6-DOF pose per sensor from each burst.

When the measurement stage has closed every window of a burst
(:class:`coiltrack.firmware.measure.burst.BurstMeasurement`), each sensor's
signal matrix is solved by the allocation-free
:class:`coiltrack.firmware.pose.solver.PoseSolver` (warm-started from the
tracked pose; Kuipers' closed form and the grid search only to acquire), and
the pose is sent as a ``POSE`` without ``POSE_FUSED``. One sensor's solve at a
time, within the tick's work budget; :meth:`MagneticTracker.on_solution` is
the hook a fusing tracker extends.
"""
from __future__ import annotations

import numpy as np

from coiltrack.protocol.schema import POSE_VALID

from coiltrack.firmware.measure.pulse import PULSE_UNUSABLE
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, PoseSolver
from coiltrack.firmware.rotation import quat_tuple
from coiltrack.firmware.track.status import COIL_FATAL, input_status

SOLVE_FAILED = SOLVE_BAD_INPUT | SOLVE_NO_START | SOLVE_NONFINITE


class TrackedPose:
    """The last magnetic solution of one sensor (position m, rotation
    sensor-to-source)."""

    def __init__(self, hemisphere):
        self.position = np.zeros(3)
        self.rotation = np.eye(3)
        self.have_pose = False
        self.hemisphere = np.array(hemisphere, dtype=float)


class MagneticTracker:
    """Solves each burst for every sensor and reports the magnetic poses."""

    def __init__(self, cfg, coils, channels, schedule, burst, supervisor, tx):
        self.cfg = cfg
        self.channels = tuple(channels)
        self.schedule = schedule
        self.burst = burst
        self.supervisor = supervisor
        self.tx = tx
        self.solver = PoseSolver(coils, cfg.field_model)
        self.nominal = np.array([c.current for c in cfg.coils])
        self.currents = np.zeros(len(coils))
        self._curv = memoryview(self.currents)
        self._nomv = memoryview(self.nominal)
        self.poses = {ch.node: TrackedPose(cfg.hemisphere) for ch in self.channels}
        self._next = -1                  # index of the next channel to solve; -1: idle
        self.cycles = 0

    # ------------------------------------------------------------ inputs
    def on_imu(self, msg, now_us: int) -> None:
        """IMU samples are not used by the magnetic-only tracker."""

    def on_mag(self, msg, lsb: float) -> None:
        """Samples of nodes that are not tracked sensors are not used."""

    def on_coil_status(self, msg) -> None:
        """The schedule keeps the driver's reports; nothing more to do."""

    def on_burst(self, t_ref: int) -> None:
        """A burst was commanded; its pose will refer to ``t_ref``."""

    # ------------------------------------------------------------ tick
    def step(self, now_us: int) -> None:
        if self._next < 0:
            if not self.burst.complete:
                return
            self._next = 0
            self._prepare_currents()
        ch = self.channels[self._next]
        self._solve_and_report(ch)
        self._next += 1
        if self._next == len(self.channels):
            self._next = -1
            self.cycles += 1
            self.burst.release()

    def _prepare_currents(self) -> None:
        """The driver's measured current where it reported one, else the nominal."""
        cur, mc, nom = self._curv, self.schedule._mv, self._nomv
        for j in range(len(cur)):
            cur[j] = mc[j] if mc[j] != 0.0 else nom[j]

    def _solve_and_report(self, ch) -> None:
        """Magnetic-only pose of one sensor from the burst's signal matrix,
        sent as a POSE without ``POSE_FUSED``; a usable solution goes to
        :meth:`on_solution`."""
        sched = self.schedule
        flags = ch.burst_flags()
        faults = sched.any_faults()
        status = input_status(flags, faults) | self.supervisor.pose_status(ch.node, flags)
        usable = not (flags & PULSE_UNUSABLE) and not (faults & COIL_FATAL) and not self.supervisor.veto
        tp = self.poses[ch.node]
        sv = self.solver
        solved = False
        if usable:
            ch.fill_sigma()
            hemi = tp.position if tp.have_pose else tp.hemisphere
            solved = not (sv.solve(ch.S, self.currents, ch.sigma, hemi) & SOLVE_FAILED)
        t_pose = (int(sched.start[0]) + int(sched.end[-1])) // 2      # the middle of the burst
        if solved:
            np.copyto(tp.position, sv.position)
            np.copyto(tp.rotation, sv.rotation)
            tp.have_pose = True
            self.tx.pose_cov6(ch.node, t_pose, tp.position, quat_tuple(tp.rotation), sv.covariance,
                              status | POSE_VALID)
        else:
            self.tx.pose_unknown(ch.node, t_pose, tp.position, quat_tuple(tp.rotation), status)
        self.on_solution(ch, solved)

    def on_solution(self, ch, solved: bool) -> None:
        """Hook: the burst of ``ch`` was solved (``self.solver`` holds it) or not."""

    def counters(self) -> dict:
        return {"cycles": self.cycles}
