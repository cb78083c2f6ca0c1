"""The fused tick on the compiled core in few calls (``track.burst_fusion.BurstFusionTracker``
``_step_fast``, ``_process_fused``, ``_send_fused_plain``; ``core/py_fusimu.c`` ``FusedTick.process``
and ``FusOutput.send``) against the reference methods (``_step``, ``_process``, ``_send_fused``,
``SensorInertial.send_fused`` with ``PoseOutput.send_plain`` and the transmitter's pose by pose
``pose_next``): a recorded roetenberg-fusion run replayed through both gives every frame the
firmware writes byte for byte, the same counters, the same tx errors on a link that fails every
seventh write, and the fast path carries the fused ticks (its hand-backs included)."""
from __future__ import annotations

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.track.burst_fusion import BurstFusionTracker
from coiltrack.tools import scenarios
from coiltrack.tools.bench.framelog import ReplayPort, log_config, read_log
from coiltrack.tools.bench.runner import run_inproc

pytestmark = pytest.mark.skipif(not core.available(), reason="compiled core not built")


@pytest.fixture(scope="module")
def fusion_log(tmp_path_factory):
    log = tmp_path_factory.mktemp("fused_tick") / "run.log"
    run_inproc(scenarios.get("roetenberg-fusion"), seed=1, duration_s=6.0, log_path=log)
    return read_log(log)


class _Port(ReplayPort):
    """The replay's port keeping every frame written; every ``fail_every``-th write raises."""

    def __init__(self, reads, fail_every: int):
        super().__init__(reads)
        self.frames, self.fail_every, self.n = [], fail_every, 0

    def write(self, data) -> None:
        self.n += 1
        if self.fail_every and self.n % self.fail_every == 0:
            raise OSError("link full")
        self.frames.append(bytes(data))


def _replay(header, reads, fast: bool, fail_every: int = 0):
    port = _Port(reads, fail_every)
    bind = BurstFusionTracker._bind_fused_tick
    if not fast:                                  # the reference methods: nothing bound at composition
        BurstFusionTracker._bind_fused_tick = lambda self, core: None
    try:
        fw = Firmware(log_config(header), port)
    finally:
        BurstFusionTracker._bind_fused_tick = bind
    tr = fw.tracker
    seen = {"fast": 0, "back": 0}
    if fast:
        assert tr.step.__func__ is BurstFusionTracker._step_fast            # bound on the compiled core
        proc = tr._ft_process

        def counted(max_steps):
            r = proc(max_steps)
            seen["fast"] += r >> 2
            seen["back"] += r & 1
            return r
        tr._ft_process = counted
    else:
        assert not {"step", "_process", "_send_fused"} & set(tr.__dict__)
    tick, end = int(header["tick_us"]), int(header["duration_s"] * 1e6)
    t = 0
    while t <= end:
        port.now_us = t
        fw.tick(t)
        t += tick
    return port.frames, fw.status(), fw.tx.tx_errors, seen


@pytest.mark.parametrize("fail_every", [0, 7])
def test_fused_tick_writes_the_reference_frames(fusion_log, fail_every):
    """Byte for byte the frames of the reference methods (POSEs, fused and magnetic, windows,
    commands, syncs, heartbeats), the same status counters and tx errors. Catches a sample counted
    twice or not at all (``imu_samples``), a sensor's ring left undrained or drained past the
    budget, a pose sent twice, out of order or with a sequence number apart from the others, and a
    failed write that stops the queue or goes uncounted."""
    header, reads = fusion_log
    f_ref, st_ref, err_ref, _ = _replay(header, reads, False, fail_every)
    f_got, st_got, err_got, seen = _replay(header, reads, True, fail_every)
    assert st_got == st_ref
    assert err_got == err_ref and (err_ref > 100) == (fail_every > 0)
    assert f_got == f_ref and len(f_ref) > 600
    # the compiled call carried the fused ticks' samples; it handed some back (the compass's
    # learning, a fusion filter not yet started), which the reference loop then ran
    assert seen["fast"] > 0.4 * st_ref["imu_samples"] > 280 and seen["back"] >= 1


def test_fused_tick_is_not_bound_where_the_reference_differs(fusion_log):
    """The Python core keeps the reference methods (no ``FusedTick``); so does a tracker class
    that overrides one of them."""
    header, reads = fusion_log
    cfg = log_config(header)
    fw = Firmware(cfg.with_(core={"impl": "python"}), ReplayPort(reads))
    assert fw.tracker.step.__func__ is BurstFusionTracker.step and not hasattr(fw.tracker, "_ft_process")

    class Own(BurstFusionTracker):
        def _send_fused(self):
            BurstFusionTracker._send_fused(self)

    fw = Firmware(cfg, ReplayPort(reads))
    tr = fw.tracker
    own = Own.__new__(Own)
    own.__dict__.update({k: v for k, v in tr.__dict__.items() if k not in ("step", "_process", "_send_fused")})
    own._bind_fused_tick(core.load("compiled"))
    assert not {"step", "_process", "_send_fused"} & set(own.__dict__)
