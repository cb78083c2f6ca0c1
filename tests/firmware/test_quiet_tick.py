"""The quiet tick: stages that keep the time of their next work and return at once until then
(supervise.timesync, supervise.health, actuate.fixed_cycle, track.burst_fusion) do what a
full scan every tick does.

Each stage is driven on seeded random inputs beside a plain reference written here, the scan
the stage did every tick before (every request and the period compared with the clock; every
node's last sign of life compared with its timeout; the cycle's next start less the lead), and
the two must act in the same ticks. The fused tracker's quiet path is checked on a bench run:
the same POSE bytes with it as with the full step forced every tick.
"""
import hashlib
import random

from coiltrack.protocol.schema import EVT_NODE_LOST

from coiltrack.firmware.actuate.fixed_cycle import FixedCycle
from coiltrack.firmware.supervise.health import Health, HealthConfig
from coiltrack.firmware.supervise.timesync import TimeSyncMaster

_REQUESTS = 6


class _ScanSync:
    """The broadcast decision of TimeSyncMaster.step as a scan of every request each tick."""

    def __init__(self, period_us: int):
        self.period_us = period_us
        self.next_us = 0
        self.req = [-1] * _REQUESTS

    def request(self, at_us: int) -> None:
        r = self.req
        for i in range(_REQUESTS):
            if r[i] < 0:
                r[i] = at_us
                return
        j = max(range(_REQUESTS), key=lambda i: (r[i], -i))
        if at_us < r[j]:
            r[j] = at_us

    def kick(self) -> None:
        self.next_us = 0

    def step(self, now_us: int) -> bool:
        due = now_us >= self.next_us
        for i in range(_REQUESTS):
            if 0 <= self.req[i] <= now_us:
                due = True
                self.req[i] = -1
        if due:
            self.next_us = now_us + self.period_us
        return due


def test_time_sync_broadcasts_in_the_ticks_a_full_scan_chooses():
    """20,000 ticks of 1 ms with requests (some in the past, some far ahead, more than the six
    slots hold at once) and kicks at random: a broadcast in exactly the ticks of the scan.
    Catches a request earlier than the kept time not lowering it, a request left pending
    when another one is sent, and a kick that waits for the period."""
    rng = random.Random(7)
    ts = TimeSyncMaster((1, 2, 9), period_us=250_000)
    ref = _ScanSync(250_000)
    sent = []
    sent_ref = []
    for tick in range(20_000):
        now = tick * 1000
        u = rng.random()
        if u < 0.02:
            for _ in range(rng.randint(1, 8)):
                at = now + rng.choice((-3000, 0, 1000, 3000, 5000, rng.randint(0, 400_000)))
                ts.request(at)
                ref.request(at)
        elif u < 0.022:
            ts.kick()
            ref.kick()
        ts.step(now, lambda master_time_us, seq: sent.append(now))
        if ref.step(now):
            sent_ref.append(now)
        assert len(sent) == len(sent_ref), now
    assert sent == sent_ref
    assert 150 < len(sent) < 2000


def test_node_loss_in_the_ticks_a_full_scan_sees_it():
    """Four sensors and a driver heard at random (some silent for seconds, some coming back):
    every EVT_NODE_LOST in the tick where ``now - last_heard > timeout`` first holds, no
    other, also after the whole bus fell silent. Catches a kept check time not lowered when a
    lost node is heard again (after a silence of all, none would be lost again) and one not
    recomputed after a loss."""
    rng = random.Random(3)
    cfg = HealthConfig(sensor_timeout_us=40_000, driver_timeout_us=90_000)
    h = Health((4, 5, 6, 7), 16, 120.0, cfg)
    ids = (4, 5, 6, 7, 16)
    timeout = {n: cfg.sensor_timeout_us for n in ids[:4]}
    timeout[16] = cfg.driver_timeout_us
    last = {n: 0 for n in ids}
    lost = {n: False for n in ids}
    quiet_until = {n: 0 for n in ids}
    events = []
    expected = []
    for tick in range(30_000):
        now = tick * 1000
        if tick % 5000 == 2500:              # the whole bus silent: every node lost
            for n in ids:
                quiet_until[n] = now + 150_000
        for n in ids:
            if now >= quiet_until[n] and rng.random() < 0.3:
                h.heard(n, now)
                last[n] = now
                lost[n] = False
                if rng.random() < 0.002:
                    quiet_until[n] = now + rng.choice((30_000, 60_000, 200_000, 1_000_000))
        h.step(now)
        for n in ids:
            if not lost[n] and now - last[n] > timeout[n]:
                lost[n] = True
                expected.append((now, n))
        h.flush_events(lambda code, detail: events.append((now, code, detail)))
    assert [(t, d) for t, code, d in events if code == EVT_NODE_LOST] == expected
    assert h.lost_events == len(expected) >= 20


def test_fixed_cycle_due_time_is_the_next_start_less_the_lead():
    """Through advances and skipped cycles (the clock jumping ahead): ``due_us`` is always
    ``cycle_start + coil * spacing_us - lead_us``, and :meth:`due` agrees with it."""
    rng = random.Random(11)
    cyc = FixedCycle(3, 50_000, 600_000, 70_000, 60_000, 2_000)
    now = 0
    for _ in range(2_000):
        now += rng.choice((1000, 1000, 1000, 37_000, 900_000))
        while cyc.due(now):
            cyc.advance(now)
            assert cyc.due_us == cyc.cycle_start + cyc.coil * cyc.spacing_us - cyc.lead_us
        assert cyc.due_us == cyc.cycle_start + cyc.coil * cyc.spacing_us - cyc.lead_us
        assert not cyc.due(now) and now < cyc.due_us
        if rng.random() < 0.05:
            cyc.skip_late(now + rng.randint(0, 2_000_000))
            assert cyc.due_us == cyc.cycle_start + cyc.coil * cyc.spacing_us - cyc.lead_us


def _pose_bytes(force_full: bool, seconds: float = 2.5) -> tuple[str, int, int]:
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    sc = scenarios.get("roetenberg-fusion")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    cfg = sc.firmware_config().validate()
    fw = Firmware(cfg, fw_end)
    tr = fw.tracker
    sent = hashlib.sha256()
    write = fw_end.write

    def record(data):
        sent.update(bytes(data))
        write(data)

    fw_end.write = record
    quiet = 0
    t = 0
    while t < seconds * 1e6:
        bench.emulator.step(t)
        if force_full:
            tr._idle = False
        elif tr._idle:
            quiet += 1
        fw.tick(t)
        t += cfg.timing.tick_us
    return sent.hexdigest(), fw.tx.fused_poses, quiet


def test_fused_tracker_quiet_ticks_send_what_the_full_step_sends():
    """roetenberg-fusion, 2.5 s: every byte the firmware sends is the same whether the fused
    tracker takes its quiet path or runs the full step every tick, and most ticks are quiet.
    Catches a quiet path taken with a sample queued, a burst complete or a fusion under way."""
    full, n_full, _ = _pose_bytes(True)
    fast, n_fast, quiet = _pose_bytes(False)
    assert n_fast == n_full > 200
    assert fast == full
    assert quiet > 1500


def _check_fused_invariants(name: str, seconds: float) -> tuple[int, int, int, int]:
    """Drive scenario ``name`` and check after every tick what the fused tracker's step leaves
    without visiting every sensor: ``_idle`` only with every IMU ring (the sensors' and the
    source's) empty, ``_n_pending`` the number of sensors with ``pending`` set, and no sensor
    left with a fused pose queued or a restart not announced. Returns the ticks with ``_idle``
    set, the fusion updates, the filters' restarts and the ticks with a source sample queued."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    cfg = sc.firmware_config().validate()
    fw = Firmware(cfg, fw_end)
    tr = fw.tracker
    sensors = tuple(tr.inertial.values())
    idle = src_queued = 0
    t = 0
    while t < seconds * 1e6:
        bench.emulator.step(t)
        fw.tick(t)
        if tr._idle:
            idle += 1
            assert tr.source.queued() == 0 and all(len(ins.imu) == 0 for ins in sensors), t
        src_queued += tr.source.queued() > 0
        assert tr._n_pending == sum(ins.pending for ins in sensors), t
        for ins in sensors:
            assert len(ins.fusion.output.out) == 0, t
            assert ins._recovery.recoveries == ins.recoveries_seen, t
        t += cfg.timing.tick_us
    return (idle, sum(ins.fusion.updates for ins in sensors), sum(ins._recovery.recoveries for ins in sensors),
            src_queued)


def test_fused_tracker_visits_only_sensors_with_work_and_leaves_none_behind():
    """roetenberg-walking-leg-loose (the source's IMU: sensor samples wait for the source's;
    the filter restarts at 2.31 s, in a tick of no IMU sample) for 2.5 s and
    roetenberg-fusion-delta (IMU_DELTA pairs: twelve steps at once, more than a tick drains)
    for 3 s: after every tick the skipped visits hid nothing (see the helper). Catches a ring
    left with samples behind a set ``_idle`` (the source's ring forgotten, a sample held back
    by the step budget), a fusing count off by an update that began or ended, and a fused pose
    or a restart's event left unsent by a tick that skipped the sensor's outputs."""
    _, _, restarts, src = _check_fused_invariants("roetenberg-walking-leg-loose", 2.5)
    assert restarts == 1 and src > 1200          # (a source sample waits in most ticks)
    idle, updates, _, _ = _check_fused_invariants("roetenberg-fusion-delta", 3.0)
    assert updates >= 4 and idle > 1500
