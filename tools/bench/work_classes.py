"""What each tick did, read from the firmware's own counters: the work classes of ``coiltrack perf``.

The tick's cost depends on which pieces of work fell into it. Each measured tick is given a
*class*: the pieces it did, in the fixed order of :data:`COMPONENTS`, joined by ``+``
(``idle``: none of them). The counters read (before and after the tick, no wrapper around any
firmware call, so the timing is the firmware's own):

``imu``          IMU samples received (``Receiver.imu_received``)
``orientation``  inclination or compass updates of an orientation filter (thesis ch. 2; each
                 ``KalmanUpdate`` applied or rejected)
``window``       pulse windows closed (``WindowCloser.closed``)
``solve``        field evaluations of any signal model (pose solves, compensation)
``update``       delayed magnetic updates of a fusion filter prepared or applied
``replay``       replay steps of a fusion filter (``FusionFilter.last_step_units``)
``pose``         POSE frames sent (``Transmitter.poses``)

Per class, :func:`summarise` gives the tick count and the CPU time's median, p99 and maximum,
and which classes the ticks at or above the run's p99.9 belong to: where the worst ticks come
from, in units a board's configuration can act on (the budgets bound ``solve`` and
``replay``; the others are one piece each).
"""
from __future__ import annotations

import numpy as np

__all__ = ["COMPONENTS", "TickWork", "label", "summarise"]

COMPONENTS = ("imu", "orientation", "window", "solve", "update", "replay", "pose")


def label(deltas) -> str:
    """The class of a tick whose counters moved by ``deltas`` (one per :data:`COMPONENTS`)."""
    parts = [name for name, d in zip(COMPONENTS, deltas) if d > 0]
    return "+".join(parts) if parts else "idle"


class TickWork:
    """The counters of one firmware, read around each tick (:meth:`begin`, :meth:`end`)."""

    def __init__(self, fw, instances):
        from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter
        from coiltrack.firmware.estimate.orientation import OrientationFilter
        from coiltrack.firmware.measure.windows import WindowCloser
        from coiltrack.firmware.model.signal import SignalModel

        self.rx = fw.receiver
        self.tx = fw.tx
        self.models = tuple(instances(fw, SignalModel))
        self.oris = tuple(instances(fw, OrientationFilter))
        self.closers = tuple(instances(fw, WindowCloser))
        self.filters = tuple(instances(fw, FusionFilter))
        self._before = (0,) * len(COMPONENTS)

    def _counters(self) -> tuple:
        return (self.rx.imu_received,
                sum(o.upd_acc.count + o.upd_acc.rejected + o.upd_mag.count + o.upd_mag.rejected
                    for o in self.oris),
                sum(c.closed for c in self.closers),
                sum(m.evals for m in self.models),
                sum(f.prepared + f.upd.count + f.upd.rejected for f in self.filters),
                sum(f.last_step_units for f in self.filters),
                self.tx.poses)

    def begin(self) -> None:
        for f in self.filters:
            f.last_step_units = 0          # set by a replay step only: zero unless one ran
        self._before = self._counters()

    def end(self) -> str:
        """The class of the tick since :meth:`begin`."""
        after = self._counters()
        return label(a - b for a, b in zip(after, self._before))


def summarise(cpu_ns, labels) -> dict:
    """``{"classes": {class: {ticks, cpu_us_median, cpu_us_p99, cpu_us_max}}`` (costliest
    maximum first), ``"p999_classes": {class: ticks}``: the classes of the ticks whose CPU
    time is at or above the run's 99.9th percentile (most first)}``."""
    c = np.asarray(cpu_ns, dtype=float) / 1e3
    lab = np.asarray(labels, dtype=object)
    out = {}
    for name in sorted(set(labels)):
        v = c[lab == name]
        out[name] = {"ticks": int(v.size), "cpu_us_median": round(float(np.median(v)), 2),
                     "cpu_us_p99": round(float(np.percentile(v, 99)), 2), "cpu_us_max": round(float(v.max()), 2)}
    classes = dict(sorted(out.items(), key=lambda kv: -kv[1]["cpu_us_max"]))
    top = {}
    if c.size:
        for name in lab[c >= np.percentile(c, 99.9)]:
            top[name] = top.get(name, 0) + 1
    return {"classes": classes, "p999_classes": dict(sorted(top.items(), key=lambda kv: -kv[1]))}
