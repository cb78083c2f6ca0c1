"""The emulator's samples computed and encoded ahead (``Emulator.prepare``,
``SensorNode.prepare_sample``), on the simulated clock:

* the byte stream is the one the sampling path alone gives, whenever the
  preparation runs (every tick, or once a sample with pulses committed after
  it), across a power cycle of the sensor (its noise draw undone) and with
  set/reset flips commanded between;
* prepared ahead, the step at a sample's instant reads no field and encodes
  no frame: it writes the prepared bytes;
* a coil current edited from a time after what was computed leaves it valid,
  one edited at or before it does not (``World.edited_since``);
* the wall-clock loop prepares outside the quiet time after a write, before
  the samples' instants.
"""
from __future__ import annotations

import select

from coiltrack.firmware.loop import Firmware
from coiltrack.hil.clock import SimClock
from coiltrack.hil.faults import BenchFaults
from coiltrack.hil.physics import CoilCurrent
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.realtime import PREFETCH_AFTER_SEND_US, PREPARE_AHEAD_US, emulator_loop
from coiltrack.tools.bench.runner import BenchSetup
from coiltrack.tools.scenarios import get

from .conftest import capture_writes, flag_inside_step


def _run(mode: str | None, faults: str | None = None, duration_us: int = 2_000_000, seed: int = 3):
    """Firmware and emulator on the simulated clock; ``mode``: None (no preparation), ``"each"``
    (``prepare`` after every tick, ``PREPARE_AHEAD_US`` ahead) or ``"once"`` (only while the sensor
    has none prepared, 9 ms ahead: pulses committed after it make some invalid at their instant).
    Returns the emulator's bytes, the sensor, the emulator and the field reads and frame encodings
    made inside the sensor's steps."""
    sc = get("roetenberg-bench")
    cfg = sc.firmware_config()
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, seed, duration_us * 1e-6, emu_end, BenchFaults.parse(faults) if faults else None, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    sensor, emu = bench.sensor, bench.emulator
    on_path = {"field": 0, "encode": 0}
    real_field = sensor.world.field_sensor_frame
    enc = emu.encoders[sensor.node_id]
    real_encode = enc.encode

    def field(t):
        on_path["field"] += inside[0]
        return real_field(t)

    def encode(msg):
        on_path["encode"] += inside[0] and msg.NAME == "MAG_PACKED"
        return real_encode(msg)
    sensor.world.field_sensor_frame, enc.encode = field, encode
    inside = flag_inside_step(sensor)
    sent = capture_writes(emu_end)
    t = 0
    while t <= duration_us:
        emu.step(t)
        fw.tick(t)
        if mode == "each":
            emu.prepare(t + PREPARE_AHEAD_US)
        elif mode == "once" and sensor.prepared_msg is None:
            emu.prepare(t + 9_000)
        t += cfg.timing.tick_us
    return bytes(sent), sensor, emu, on_path


def test_prepared_samples_give_the_same_bytes_and_leave_only_a_write_at_the_instant():
    """Prepared at every tick, the emulator sends the very bytes of the sampling path (a
    preparation that drew its noise out of order, missed a commanded flip or its artefact, took
    the stamp early or encoded at a stale sequence number changes a frame), and at each
    sample's instant it reads no field and encodes no frame: every sample goes as prepared."""
    plain, s0, _, path0 = _run(None)
    ahead, s1, emu, path1 = _run("each")
    assert s1.samples == s0.samples >= 200
    assert len(s1.flip_log) == len(s0.flip_log) >= 4 and any(f["commanded"] for f in s1.flip_log)
    assert ahead == plain
    assert path0["field"] >= s0.samples and path0["encode"] == s0.samples
    assert s1.prepared_used == s1.samples and s1.prepared_redone == 0
    assert path1["field"] == 0
    # the prepared bytes go out as encoded, but where the node sent a frame of its own in the
    # same step before the sample (a heartbeat, a sync reply): encoded again at the instant
    assert emu.ready_sent == s1.samples - path1["encode"] and path1["encode"] <= 4


def test_a_sample_prepared_before_a_pulse_was_committed_is_computed_again_with_its_noise():
    """Prepared 9 ms ahead and not again, some samples see a pulse committed after their
    preparation that starts before them: those are computed on the sampling path with the noise
    drawn for them, and the bytes are still the same (a check that misses the edit sends a field
    without the pulse; a redo that draws its noise again shifts every later sample's)."""
    plain, s0, _, _ = _run(None)
    ahead, s1, _, _ = _run("once")
    assert ahead == plain
    assert s1.prepared_redone >= 3 and s1.prepared_used >= s1.samples // 2
    assert s1.prepared_used + s1.prepared_redone == s1.samples


def test_a_power_cycle_undoes_the_prepared_sample_draw():
    """The sensor is off from 0.8 s to 1.1 s: the sample prepared before it is never sent, its
    noise draw is undone before the reboot's schedule draw, and the bytes stay those of the
    sampling path (a dropped preparation that keeps its draw shifts every sample after the
    reboot)."""
    f = "node_off=sensor@0.8s-1.1s"
    plain, s0, _, _ = _run(None, f)
    ahead, s1, _, _ = _run("each", f)
    assert s1.reboots == s0.reboots == 1
    assert ahead == plain
    assert s1.prepared_used == s1.samples


def test_a_current_edit_invalidates_only_what_it_changes():
    """``CoilCurrent.edited_since(mark, t)``: a pulse or a ripple span added after the mark that
    starts at or before ``t`` (the current there changed), not one that starts after it; a pulse
    cutting an earlier one short counts from its own start. ``World.edited_since`` over every
    coil, and any object added."""
    c = CoilCurrent(tau_rise_s=1e-4)
    c.add_pulse(1_000, 2_000, 1.0)
    m = c.edits
    assert not c.edited_since(m, 10_000)
    c.add_pulse(20_000, 1_000, 1.0)
    assert not c.edited_since(m, 19_999) and c.edited_since(m, 20_000)
    m = c.edits
    c.add_pulse(2_500, 1_000, -1.0)          # cuts the first short at 2 500: earlier values hold
    assert not c.edited_since(m, 2_499) and c.edited_since(m, 2_500)
    assert abs(c.current_at(2_499) - c.current_at(2_499)) == 0.0
    m = c.edits
    c.add_ripple(30_000, 31_000, 0.01, 20e3, 0.0)
    assert not c.edited_since(m, 29_999) and c.edited_since(m, 30_000)

    sc = get("roetenberg-bench")
    world = sc.build_world(1, 1.0)
    mark = world.edit_mark()
    world.currents[2].add_pulse(50_000, 1_000, 0.5)
    assert not world.edited_since(mark, 49_999) and world.edited_since(mark, 50_000)
    mark = world.edit_mark()
    world.add(type("Obj", (), {"active": lambda self, t: False})())
    assert world.edited_since(mark, 0)


class _PrepEmu:
    """An emulator whose samples are due at ``due`` (us), recording its prepare calls and the
    steps that took a sample (``steps_with``: the sample was prepared by then)."""

    def __init__(self, clock, due):
        self.clock = clock
        self.due = list(due)
        self.prepared = None
        self.prepares = []
        self.steps = []
        self.recorder = type("R", (), {"poses": []})()

    def next_due_us(self):
        return self.due[0] if self.due else None

    def step(self, now):
        taken = self.due and self.due[0] <= now
        self.steps.append((now, bool(taken), taken and self.prepared == self.due[0]))
        while self.due and self.due[0] <= now:
            self.due.pop(0)

    def prepare(self, until):
        nxt = self.next_due_us()
        if nxt is None or nxt > until or self.prepared == nxt:
            return 0
        self.prepares.append((self.clock.now(), nxt))
        self.prepared = nxt
        self.clock.now_us += 300
        return 1


class _WritingLink:
    def __init__(self, emu):
        self.emu, self.bytes_tx = emu, 0

    def flush(self):
        if self.emu.steps and self.emu.steps[-1][1]:
            self.bytes_tx += 10          # a step that took a sample wrote it


def test_emulator_loop_prepares_each_sample_before_its_instant_outside_the_quiet_time():
    """Each sample is prepared before its instant (a loop that never calls ``prepare`` computes
    every sample on the sampling path), never within PREFETCH_AFTER_SEND_US after a step that
    wrote (there the firmware's answer comes and the tty's flush work runs), and not earlier
    than PREPARE_AHEAD_US before its instant."""
    clock = SimClock(-1_000)
    due = [1_000, 9_333, 17_666, 26_000]
    emu = _PrepEmu(clock, due)
    emulator_loop(emu, _WritingLink(emu), clock, 30_000, step_us=250, wait=clock.sleep)
    taken = [s for s in emu.steps if s[1]]
    assert [s[0] for s in taken] == due
    assert all(s[2] for s in taken[1:])                   # after the first: each prepared in time
    for at, nxt in emu.prepares:
        assert nxt - at <= PREPARE_AHEAD_US
        assert not [d for d in due if d <= at < d + PREFETCH_AFTER_SEND_US]


def test_an_urgent_frame_leaves_at_once_with_what_was_queued_before_it():
    """The firmware's pty link (``open_pty_slave``) queues a tick's frames but sends a ``POSE`` as
    it is written, with the frames queued before it, in order (a link that waits for the tick's
    end delays every pose by the work after the report). The id is read at the COBS frame's
    sixth byte whatever zeros the header holds (flags 0, sequence 0); a byte equal to the id
    elsewhere in another message does not count."""
    import os

    from coiltrack.protocol import MSG, FrameEncoder
    from coiltrack.protocol.framing import encode_frame
    from coiltrack.tools.bench.links import FdLink, make_raw_pty

    pose_id = MSG["POSE"].ID
    master, slave, _ = make_raw_pty()
    try:
        link = FdLink(slave, coalesce=True, urgent=(pose_id,))
        hb = FrameEncoder(1).encode(MSG["HEARTBEAT"](1, 2, pose_id, pose_id, pose_id, 0))
        link.write(hb)
        assert link.writes == 0 and hb[5] != pose_id and pose_id in hb
        pose = encode_frame(MSG["POSE"](16, 0, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 1, 255), 0, 1)
        link.write(pose)
        assert link.writes == 1 and link.bytes_tx == len(hb) + len(pose)
        link.write(hb)
        assert link.writes == 1
        link.flush()
        assert link.writes == 2
        got = b""
        for _ in range(200):
            select.select([master], [], [], 0.05)
            got += os.read(master, 4096)
            if len(got) >= 2 * len(hb) + len(pose):
                break
        assert got == hb + pose + hb
    finally:
        os.close(master)
        os.close(slave)
