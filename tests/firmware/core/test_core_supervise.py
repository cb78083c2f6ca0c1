"""The supervisor's kernels (firmware_py/core/src/supervise.c, py_supervise.c) against their
Python references, ``Supervisor.on_message`` for a MAG_SAMPLE (``Health.heard``,
``FlipScheduler.observe``, ``Supervisor._quiet``, ``Health.on_mag``), for a
TIME_SYNC_REPLY (``Health.heard``, ``TimeSyncMaster.on_reply``, ``Health.on_sync_reply``, the
stamps restarted while a node acquires) and ``Supervisor.pose_status``, and the burst's MAG_FLIP_CMD frame (``flip_frame``) against
``protocol.framing.encode_frame``.

Two supervisors get the same seeded stream of samples (several sensors, the coil driver and an
unknown node; stamps on the sample grid, jittered, stepped, duplicated and from the future;
saturated samples; sync replies, some answering broadcasts, some showing clock steps, some from
the driver and an unknown node; quiet fields that learn their reference and then drift past the distortion
threshold and back; pulses moving over the stamps), sync replies that show clock steps and
silences that lose nodes, coil statuses with faults and new bursts: one through ``on_message`` alone, one through the kernel with
``on_message`` for what the kernel hands back. After every message their whole per-node state,
counters and events must be equal, the floats bit for bit, and the two must give every pose the
same status bits and veto. Catches a dropped case (the kernel
writing where the reference raises an event), an off-by-one in the state layout, a stamp tolerance
compared the wrong way, a magnitude from the wrong set/reset slot. Seeded; skips without the
extension."""
import dataclasses
import random

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.supervise.health import Health
from coiltrack.firmware.supervise.supervisor import Supervisor
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol import MSG
from coiltrack.protocol.codec import STRUCTS
from coiltrack.protocol.framing import encode_frame
from coiltrack.protocol.schema import MAG_LSB_T, POSE_COIL_FAULT, POSE_DISTORTED, POSE_INCONSISTENT

ext = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")
SENSORS = (16, 17, 18, 40)
_MAG, _REPLY = MSG["MAG_SAMPLE"], MSG["TIME_SYNC_REPLY"]
STRUCT_REPLY = STRUCTS[_REPLY.ID]
#: the frame decoder's payload table the reply kernel reads (a reply at offset 40)
PAYLOADS = bytearray(128)


class _Schedule:
    def __init__(self, n):
        self.start = np.zeros(n, dtype=np.int64)
        self.end = np.zeros(n, dtype=np.int64)
        self.pulse_id = np.zeros(n, dtype=np.int64)
        self.burst_start = None
        self.burst_end = 0


class _Tx:
    def __init__(self):
        self.sent, self.events = [], []

    def send(self, msg):
        self.sent.append(msg)

    def time_sync(self, master_time_us, seq):
        self.sent.append(MSG["TIME_SYNC"](master_time_us, seq))

    def event(self, code, detail):
        self.events.append((code, detail))

    def mag_flip(self, node, at_us, state):
        self.sent.append(MSG["MAG_FLIP_CMD"](node, at_us, state))


def _pair():
    cfg = FirmwareConfig()
    cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, sensor_ids=SENSORS))
    sched = _Schedule(len(cfg.source.coils))
    sups = [Supervisor(cfg, sched, _Tx()) for _ in range(2)]
    kernel = sups[1].mag_kernel(COMPILED, PAYLOADS)
    assert kernel is not None and sups[0].mag_kernel(core.load("python")) is None
    return sched, sups, kernel


def _state(sup):
    h = sup.health
    d = {name: [float(v) if name in Health.FLOAT_LISTS else int(v) for v in getattr(h, name)]
         for name in Health.INT_LISTS + Health.FLOAT_LISTS + ("ref_n", "dist_state")}
    d["flips"] = [int(v) for v in sup.flips.state]
    d["check_us"] = int(h.check_us)
    d["susp"] = ([list(r) for r in h.susp_t0], [list(r) for r in h.susp_t1], list(h.susp_k),
                 list(h.suspect_quiet_replies))
    d["counters"] = sup.counters()
    d["events"] = h.events_queued, list(h._ev_code), list(h._ev_detail)
    ts = sup.timesync
    d["timesync"] = {name: [int(v) for v in getattr(ts, name)] for name in ts.NODE_LISTS + ("_sent_seq", "_sent_t")}
    d["timesync"]["hist"] = [[int(v) for v in r] for r in ts._hist]
    d["timesync"]["steps"] = list(ts.steps)
    return d


def _floats_bitwise(a, b):
    for name in Health.FLOAT_LISTS:
        assert np.array_equal(np.array(a[name]).view(np.int64), np.array(b[name]).view(np.int64)), name


def test_mag_kernel_follows_on_message_through_every_case():
    rng = random.Random(3)
    sched, (ref, fast), kernel = _pair()
    P = 1e6 / ref.cfg.pulse.mag_rate_hz
    stamp = {n: 0 for n in SENSORS}
    level = {n: 50e-6 for n in SENSORS}
    now = 1000
    handed_back = flag_changes = pose_bits = vetoes = replies_back = replies_done = 0
    reply = fast.reply_kernel()
    offset = {}
    flags = list(ref.health.distorted)
    for k in range(30000):
        now += rng.choice((1500, 2300, 2300, 3000))     # a little more than 1 / (rate x sensors)
        if rng.random() < 0.001:
            now += 400_000                              # a silence: nodes get lost, then come back
        if k % 300 == 0:                                # the pulses move (sometimes over the stamps)
            base = now + rng.randrange(-20_000, 20_000)
            for j in range(len(sched.start)):
                sched.start[j] = base + 4000 * j
                sched.end[j] = sched.start[j] + 2000
        if k % 2000 == 1000:                            # metal comes near the sensors, then goes
            for n in SENSORS:
                level[n] += 3e-6 if k % 4000 == 1000 else -3e-6
        r = rng.random()
        node = rng.choice(SENSORS) if r < 0.97 else rng.choice((2, 99))
        if rng.random() < 0.01:                         # a broadcast (the replies' round trips)
            for s in (ref, fast):
                s.timesync.kick()
                s.timesync.step(now, s.tx.time_sync)
        if r > 0.95:                                    # a sync reply (a few show a step)
            seq = (ref.timesync.seq - rng.randrange(1, 20)) & 0xFFFF
            off = offset.setdefault(node, rng.randrange(-3000, 3000))
            if rng.random() < 0.02:
                off = offset[node] = off + rng.choice((-5000, 5000))
            msg = _REPLY(rng.choice(SENSORS + (2, 2, 99)), seq, now + off, off + rng.randrange(-200, 200),
                         rng.randrange(-50_000, 50_000))
            ref.on_message(msg, now)
            STRUCT_REPLY.pack_into(PAYLOADS, 40, *msg)
            if reply(40, now):
                replies_back += 1
                fast.on_message(msg, now)
            else:
                replies_done += 1
        else:
            t = stamp.get(node, now)
            c = rng.random()
            if c < 0.9:
                t += int(P)
            elif c < 0.93:
                t += int(P) + rng.randrange(-900, 900)   # jitter, past the tolerance now and then
            elif c < 0.95:
                t -= rng.randrange(0, 3 * int(P))        # a duplicate or a delayed frame
            elif c < 0.96:
                t += rng.randrange(10_000, 80_000)       # a clock step forward
            elif c < 0.97:
                t = now + 10_000                          # from the future
            else:
                t += 2 * int(P)                           # a lost sample
            if node in stamp:
                stamp[node] = max(stamp[node], t) if rng.random() < 0.9 else t
            flip = rng.randrange(2) | (2 if rng.random() < 0.01 else 0)
            b = level.get(node, 50e-6) + rng.gauss(0, 0.2e-6) + (1e-6 if flip & 1 else 0.0)
            x, y, z = (int(round(b * f / MAG_LSB_T)) for f in (0.6, 0.0, 0.8))
            x += rng.randrange(-3, 4)
            msg = _MAG(node, t, x, y, z, flip)
            ref.on_message(msg, now)
            if kernel(node, t, x, y, z, flip, now):
                handed_back += 1
                fast.on_message(msg, now)
        if rng.random() < 0.2:
            for s in (ref, fast):
                s.health.step(now)
        if rng.random() < 0.05:                         # a coil's status (faults now and then), a new burst
            c, faults = rng.randrange(len(sched.start)), rng.choice((0, 0, 0, 1, 2, 4, 8, 16))
            st = MSG["COIL_STATUS"](c, int(sched.pulse_id[c]), 1000, int(sched.start[c]), int(sched.end[c]), faults)
            renew = rng.random() < 0.3
            for s in (ref, fast):
                s.on_message(st, now)
                if renew:
                    s.health.new_burst()
        if rng.random() < 0.1:                          # a pose's status: bits, veto and the count agree
            node, flags = rng.choice(SENSORS + (2, 99)), rng.choice((0, 0, 1, 2, 4, 8, 16, 32, 64, 128))
            got = [(s.pose_status(node, flags), s.veto, s.poses_vetoed) for s in (ref, fast)]
            assert got[0] == got[1], (k, got)
            pose_bits |= got[0][0]
            vetoes += got[0][1]
        flags_set = list(ref.health.distorted)
        if flags_set != flags:
            flag_changes += 1
            flags = flags_set
        a, b = _state(ref), _state(fast)
        assert a == b, k
        _floats_bitwise(a, b)
    h = ref.health
    # every case was met: the kernel handed back the rare ones and did the rest
    assert h.lost_events and h.back_events and h.clock_steps and h.saturation_events and flag_changes >= 4
    assert 1000 < handed_back < 15000              # (the stream is rich in rare cases on purpose)
    assert fast.pose_status == fast._pose_status_compiled and vetoes > 100
    assert replies_done > 200 and replies_back > 20 and sum(ref.timesync.steps) > 5 and max(ref.timesync.rtt_us)
    assert pose_bits & POSE_COIL_FAULT and pose_bits & POSE_INCONSISTENT and pose_bits & POSE_DISTORTED
    assert min(h.ref_n) == 0 and max(h.ref_n) >= h.hcfg.distortion_learn_samples


def test_flip_frame_is_encode_frame_and_the_transmitter_sends_it_on_both_cores():
    rng = random.Random(5)
    F = MSG["MAG_FLIP_CMD"]
    for _ in range(3000):
        seq, src, node = rng.randrange(256), rng.randrange(256), rng.randrange(256)
        at = rng.choice((0, (1 << 64) - 1, rng.randrange(1 << 40)))
        state = rng.randrange(2)
        assert ext.flip_frame(seq, src, node, at, state) == encode_frame(F(node, at, state), seq, src)
    for bad in ((0, 1, 256, 0, 0), (0, 1, -1, 0, 0), (0, 1, 1, -1, 0), (0, 1, 1, 1 << 64, 0), (0, 1, 1, 0, 256)):
        assert ext.flip_frame(*bad) is None

    class Port:
        def __init__(self):
            self.data = bytearray()

        def write(self, b):
            self.data += b

    outs = []
    for c in (core.load("python"), COMPILED):
        port = Port()
        tx = Transmitter(port, 1, 10**9, None, core=c)
        for i in range(300):
            tx.mag_flip(16 + i % 5, 1000 * i, i & 1)
        tx.mag_flip(300, 0, 0)                          # refused: a tx error, the sequence unmoved
        tx.mag_flip(17, 5, 1)
        outs.append((bytes(port.data), tx.tx_errors))
    assert outs[0] == outs[1] and outs[0][1] == 1


def test_pose_status_at_the_edges_of_the_span():
    """A sensor's clock was suspect in [a, b] (a sync reply showed a step): its pose is inconsistent
    and vetoed exactly when the burst's span, its pulses widened by baseline + guard before and
    fall + baseline after, meets [a, b] (a closed form); both cores agree to the microsecond at each
    edge, and the other sensors' poses are untouched. Catches a widening dropped or swapped, an
    open interval end, the driver's intervals not looked at."""
    sched, (ref, fast), kernel = _pair()
    p = ref.cfg.pulse
    before, after = p.baseline_us + p.guard_us, p.fall_us + p.baseline_us
    a, b = 1_000_000, 1_004_000
    for s in (ref, fast):
        s.health.on_sync_reply(17, True, a, b)
    n = len(sched.start)
    for lo_edge in (-1, 0, 1):
        for hi_edge in (-1, 0, 1):
            for first, last in ((0, n - 1), (n - 1, 0)):
                # the span ends at a + hi_edge (a pulse ending there), or starts at b + lo_edge
                for which in ("end", "start"):
                    for j in range(n):
                        sched.start[j], sched.end[j] = 500_000 + 1000 * j, 500_500 + 1000 * j
                    if which == "end":
                        sched.end[last] = a + hi_edge - after
                        sched.start[last] = sched.end[last] - 500
                        sched.start[first] = min(int(sched.start[first]), int(sched.start[last]))
                    else:
                        sched.start[first] = b + lo_edge + before
                        for j in range(n):
                            sched.start[j] = max(int(sched.start[j]), b + lo_edge + before)
                            sched.end[j] = sched.start[j] + 500
                        sched.start[first] = b + lo_edge + before
                    t0 = int(sched.start.min()) - before
                    t1 = int(sched.end.max()) + after
                    want = t0 <= b and t1 >= a
                    for node in (17, 16):
                        got = [s.pose_status(node, 0) for s in (ref, fast)]
                        assert got[0] == got[1]
                        assert bool(got[0] & POSE_INCONSISTENT) == (want and node == 17), (which, lo_edge, hi_edge)
    # the driver's suspect interval makes every sensor's pose inconsistent
    for s in (ref, fast):
        s.health.on_sync_reply(ref.driver_id, True, a, b)
    sched.start[:], sched.end[:] = a, a + 500
    assert all(s.pose_status(16, 0) & POSE_INCONSISTENT and s.veto for s in (ref, fast))
