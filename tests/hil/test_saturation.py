"""Every emulated sensor driven far past its range, through the node, the codec and the
firmware's receive stage: no exception, each axis clipped at the full scale (closed forms), the
saturation flag where the hardware sets it, and the firmware counting the clipped samples
instead of using them.

The world: the sensor circles a point 25 cm from the source at ``OMEGA`` = 60 rad/s on a 5 cm
radius, turning with it (body rate (0, 0, 60) rad/s, centripetal acceleration ``OMEGA^2 r`` =
180 m/s^2), so the specific force in the sensor frame is the constant ``(-OMEGA^2 r, 0, g)``;
and a magnet on the board adds 1 mT along the sensor's x axis (the magnetometer's range is
163.835 uT)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coiltrack.firmware.receive import Receiver
from coiltrack.hil import motion
from coiltrack.hil import physics as ph
from coiltrack.hil.bench import assemble
from coiltrack.hil.imu import SourceImuNode
from coiltrack.hil.imu_delta import FRAME_MAX, DeltaIntegrator
from coiltrack.hil.nodes import ImuSpec, MagSpec
from coiltrack.hil.world import HardIron, World
from coiltrack.protocol import MSG, FrameDecoder, FrameEncoder
from coiltrack.protocol.schema import (ACC_LSB, DANG_LSB_RAD, GYR_LSB, IMU_CLIP_COUNTS, MAG_LSB_T, STAMP_DVEL,
                                       STAMP_SATURATED)
from coiltrack.tools.bench.links import inproc_pair

OMEGA = 60.0          # rad/s
RADIUS = 0.05         # m
CENTRE = np.array([0.25, 0.0, 0.0])
G = 9.81


class Whirl(motion.Trajectory):
    """On a circle about ``CENTRE`` (axis z) at ``OMEGA``, the sensor's x axis pointing outward."""

    def _eval(self, t):
        c, s = np.cos(OMEGA * t), np.sin(OMEGA * t)
        z = np.zeros_like(t)
        p = CENTRE + RADIUS * np.stack([c, s, z], axis=1)
        v = RADIUS * OMEGA * np.stack([-s, c, z], axis=1)
        a = -RADIUS * OMEGA ** 2 * np.stack([c, s, z], axis=1)
        R = np.zeros((t.size, 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        w = np.tile([0.0, 0.0, OMEGA], (t.size, 1))
        return p, v, a, R, w


def _world():
    return World(ph.thesis_source(), Whirl(), objects=[HardIron([1e-3, 0.0, 0.0])])


class _Tracker:
    """Records what the receive stage hands on."""

    def __init__(self):
        self.imu = []

    def on_imu(self, msg, now_us):
        self.imu.append((msg.t_us, msg.ax, msg.ay, msg.az, msg.gx, msg.gy, msg.gz))

    def on_mag(self, msg, lsb):
        pass

    def on_coil_status(self, msg):
        pass


class _Quiet:
    def __init__(self):
        self.imu_saturated = []

    def on_message(self, msg, now_us):
        pass

    def on_imu_saturated(self, node, now_us):
        self.imu_saturated.append((node, now_us))

    def on_status(self, msg):
        pass

    def event(self, *a):
        pass


class _Bytes:
    """A port the test fills."""

    def __init__(self):
        self.buf = b""

    def read(self):
        out, self.buf = self.buf, b""
        return out


def _receiver(step_us=1e4, interval_us=1e5):
    port, tracker = _Bytes(), _Tracker()
    rx = Receiver(port, FrameDecoder(), [], _Quiet(), tracker, _Quiet(), _Quiet(),
                  imu_interval_us=interval_us, imu_step_us=step_us)
    return rx, port, tracker


def _run(imu: ImuSpec, seconds=0.6):
    """The bench's sensor node in the whirl, synchronised by a scripted master; every frame it
    sent (decoded) with its arrival time, the raw bytes, and the node."""
    port, emu_end = inproc_pair()
    bench = assemble(_world(), emu_end, mag=MagSpec(), imu=imu, seed_driver=1, seed_sensor=2, seed_faults=3,
                     seed_clocks=4, clock_drift_ppm=30.0)
    enc, dec = FrameEncoder(1), FrameDecoder()
    frames, raw = [], []
    for k, t in enumerate(range(0, int(seconds * 1e6) + 1, 1000)):
        if t % 100_000 == 0:
            port.write(enc.encode(MSG["TIME_SYNC"](t, k & 0xFFFF)))
        bench.emulator.step(t)          # raises nothing: that is the first check
        b = port.read()
        raw.append((t, b))
        frames += [(t, m) for m in dec.feed(b)]
    return frames, raw, bench.sensors[0]


def test_imu_sample_and_magnetometer_clip_at_full_scale_and_flag_it():
    """IMU_SAMPLE: ax at -32767 (180 m/s^2 > 32.767), gz at +32767 (60 > 16.38 rad/s), ay and az
    the true 0 and g (within bias and noise: 0.02 m/s^2 bias sigma, 14 mm/s^2 noise; 200 counts);
    every sample counted as saturated on the node. MAG_PACKED: x at +32767 counts (1 mT > 163.8
    uT) with the saturated bit on every sample. Catches an axis wrapped instead of clipped (a
    sign flip), a clip at -32768 the receiver's rule does not treat alike, or a lost flag."""
    frames, _, node = _run(ImuSpec(rate_hz=100.0))
    imu = [m for _, m in frames if m.NAME == "IMU_SAMPLE"]
    mag = [m for _, m in frames if m.NAME == "MAG_PACKED"]
    assert len(imu) >= 40 and len(mag) >= 40
    full_acc = round(min(ImuSpec().acc_range, IMU_CLIP_COUNTS * ACC_LSB) / ACC_LSB)
    full_gyr = round(min(ImuSpec().gyro_range, IMU_CLIP_COUNTS * GYR_LSB) / GYR_LSB)
    assert full_acc == full_gyr == IMU_CLIP_COUNTS == 32767
    for m in imu:
        assert m.ax == -full_acc and m.gz == full_gyr
        assert abs(m.ay) < 200 and abs(m.az - round(G / ACC_LSB)) < 200
        assert abs(m.gx) < 200 and abs(m.gy) < 200        # bias 8.7e-3 rad/s: 17 counts sigma
    assert node.imu_saturated == node.imu_samples >= len(imu)
    for m in mag:
        assert m.x == round(MagSpec().range_t / MAG_LSB_T) == 32767
        assert m.stamp & STAMP_SATURATED
    assert node.saturations == node.samples


def test_a_part_with_a_smaller_range_clips_at_its_own_full_scale():
    """ImuSpec.clip against the closed form: a 300 deg/s gyroscope and a 2 g accelerometer clip at
    5.236 rad/s and 19.62 m/s^2 and say so; inside the range nothing changes; on the wire a
    clipped axis is the clip code whatever the part's range (the receiver's one rule)."""
    spec = ImuSpec(acc_range=2 * G, gyro_range=math.radians(300.0))
    f, w, sf, sw = spec.clip([-50.0, 3.0, 9.0], [0.1, -9.0, 0.2])
    assert sf and sw
    np.testing.assert_allclose(f, [-2 * G, 3.0, 9.0])
    np.testing.assert_allclose(w, [0.1, -math.radians(300.0), 0.2])
    counts, sf, sw = spec.sample_counts([-50.0, 3.0, 9.0], [0.1, -9.0, 0.2])
    assert counts == [-IMU_CLIP_COUNTS, 3000, 9000, 200, -IMU_CLIP_COUNTS, 400] and sf and sw
    f2, w2, sf2, sw2 = spec.clip([1.0, 2.0, 3.0], [0.5, 0.5, 0.5])
    assert not sf2 and not sw2
    counts, sf, sw = ImuSpec().sample_counts([32.7669, 0.0, 0.0], [0.0] * 3)   # the default: the field clips
    assert counts[0] == IMU_CLIP_COUNTS - 1 and not sf


def test_delta_pairs_carry_the_saturated_bit_and_the_clipped_rotation():
    """IMU_DELTA at 20 Hz (5 samples of 100 Hz): both frames of every pair have stamp bit 14; the
    delta angle's z sum grows by the clipped rate times the interval, 16.3835 rad/s x 0.05 s /
    5e-5 rad = 16383.5 counts (the clock's 30 ppm and the rounding: 2 counts); the delta velocity's
    x by the clipped specific force -32.767 m/s^2 turned over the interval, 2 sin(wT/2)/w x f
    (wT/2 = 0.41 rad: 1 % for the sub-step rule and the bias)."""
    frames, _, node = _run(ImuSpec(rate_hz=100.0, delta_rate_hz=20.0))
    d = [m for _, m in frames if m.NAME == "IMU_DELTA"]
    assert len(d) >= 16 and not any(m.NAME == "IMU_SAMPLE" for _, m in frames)
    assert all(m.stamp & STAMP_SATURATED for m in d)
    ang = [m for m in d if not m.stamp & STAMP_DVEL]
    vel = [m for m in d if m.stamp & STAMP_DVEL]
    T = 0.05
    wc = IMU_CLIP_COUNTS * GYR_LSB
    for a, b in zip(ang, ang[1:]):
        dz = ((b.z - a.z + 32768) & 0xFFFF) - 32768
        assert abs(dz - wc * T / DANG_LSB_RAD) <= 2.0
    want_vx = 2 * math.sin(wc * T / 2) / wc * (-IMU_CLIP_COUNTS * ACC_LSB) / 1e-4
    for a, b in zip(vel, vel[1:]):
        dx = ((b.x - a.x + 32768) & 0xFFFF) - 32768
        assert abs(dx - want_vx) <= 0.01 * abs(want_vx)
    assert node.imu_saturated == node.imu_samples


def test_delta_beyond_a_frame_is_clipped_and_flagged():
    """A delta angle over one interval above what a frame's difference carries (2 rad about x in
    0.1 s, 20 rad/s unclipped) is clipped to FRAME_MAX counts and flagged, so the receiver's
    difference keeps its sign (an unclipped 40000 counts would wrap to -25536)."""
    integ = DeltaIntegrator(10, 0.01)
    for _ in range(10):
        out = integ.add([20.0, 0.0, 0.0], [0.0, 0.0, G])
    a, v = out
    assert a[0] == FRAME_MAX and integ.sat_a and not integ.sat_v
    for _ in range(10):
        out = integ.add([0.1, 0.0, 0.0], [0.0, 0.0, G], sat_f=True)
    assert not integ.sat_a and integ.sat_v
    assert ((int(out[0][0]) - int(a[0]) + 32768) & 0xFFFF) - 32768 == round(0.1 * 0.1 / DANG_LSB_RAD)


def test_source_module_clips_too():
    """The source module (hil.imu) through the same rule: fixed and level, its samples are not
    saturated; a part whose accelerometer range is below g (0.5 g) clips az at the clip code."""
    from coiltrack.hil.world import World as W

    world = W(ph.thesis_source(), motion.StaticPose([0.2, 0.0, 0.0]))
    sent = []
    node = SourceImuNode(8, world, imu=ImuSpec(rate_hz=100.0, acc_range=0.5 * G), seed=3)
    node.sync.update(0, 0)
    node.synced_since_us = 0
    node._schedule(0)
    for t in range(0, 200_001, 1000):
        node.step(t, lambda n, m: sent.append(m))
    imu = [m for m in sent if m.NAME == "IMU_SAMPLE"]
    assert len(imu) >= 15
    assert all(m.az == IMU_CLIP_COUNTS for m in imu)
    assert node.imu_saturated == node.imu_samples


def test_the_firmware_counts_clipped_samples_and_does_not_use_them():
    """The node's frames (the whirl, IMU_SAMPLE) through the firmware's receive stage: every
    sample has a clipped axis, so none reaches the tracker and all are counted. Fails if the
    receiver hands on the clip value as a measurement (a tracker would turn at 16.38 rad/s
    instead of 60)."""
    _, raw, node = _run(ImuSpec(rate_hz=100.0))
    rx, port, tracker = _receiver()
    for t, b in raw:
        port.buf = b
        rx.step(t)
    assert tracker.imu == []
    assert rx.imu_saturated == node.imu_samples > 0
    assert rx.counters()["imu_saturated"] == rx.imu_saturated


def test_the_receiver_uses_a_sample_within_range_and_skips_a_clipped_pair():
    """One IMU_SAMPLE inside the range reaches the tracker unchanged, one at -32768 (beyond the
    clip code) does not. IMU_DELTA: anchor, a saturated pair (not used, its 10 steps counted),
    then a clean pair whose steps carry its own interval's mean only (the saturated pair's sums
    anchored it): 0.2 rad over 0.1 s about z = 2 rad/s = 4000 gyro counts, not the sum of both."""
    rx, port, tracker = _receiver()
    enc = FrameEncoder(16)
    imu = MSG["IMU_SAMPLE"]
    port.buf = enc.encode(imu(16, 1000, 10, -20, 9810, 5, 6, 7)) + enc.encode(imu(16, 2000, 10, -32768, 9810, 5, 6, 7))
    rx.step(3000)
    assert tracker.imu == [(1000, 10, -20, 9810, 5, 6, 7)] and rx.imu_saturated == 1
    tracker.imu.clear()
    delta = MSG["IMU_DELTA"]

    def pair(t_us, az, vz, sat=0):
        st = (t_us // 8) & 0x3FFF
        return (enc.encode(delta(16, 0, 0, az, st | sat)) + enc.encode(delta(16, 0, 0, vz, st | STAMP_DVEL)))

    for t, b in ((100_000, pair(100_000, 0, 0)), (200_000, pair(200_000, 20000, 981, STAMP_SATURATED)),
                 (300_000, pair(300_000, 20000 + 4000, 1962))):
        port.buf = b
        rx.step(t + 1000)
    assert rx.imu_saturated_pairs == 1 and rx.imu_saturated == 1 + 10
    # the supervisor heard of each: the clipped sample at its arrival, the saturated pair once
    assert rx.supervisor.imu_saturated == [(16, 3000), (16, 201_000)]
    assert len(tracker.imu) == 10
    for t, ax, ay, az, gx, gy, gz in tracker.imu:
        assert 200_000 < t < 300_000
        assert gz == pytest.approx(0.2 / 0.1 / GYR_LSB) and az == pytest.approx(981 * 1e-4 / 0.1 / ACC_LSB)


def test_fast_magnetometer_flags_every_clipped_sample():
    """MMC5983MA (+-8 G, 18 bits around 131072): a field far above the range (+-20 G) reads the
    end codes 262143 and 0 and is flagged; a field at exactly +8 G is clipped to the top code
    (one count below the null-symmetric full scale) and is flagged too; 7 G is not."""
    from coiltrack.hil.magnetometers import FastMagProfile

    m = FastMagProfile.mmc5983ma()
    quiet = FastMagProfile(m.name, m.rate_hz, m.integration_s, m.bandwidth_hz, 0.0, m.lsb_t, m.range_t, m.null_counts)
    t = quiet.sample_times(4)
    for b, code, sat in ((20e-4, 262143, True), (-20e-4, 0, True), (8e-4, 262143, True), (7e-4, None, False)):
        counts, flags = quiet.sample(lambda s: np.tile([b, 0.0, 0.0], (s.size, 1)), t, np.random.default_rng(1))
        assert bool(flags.all()) is sat and not (flags.any() and not sat)
        if code is not None:
            assert (counts[:, 0] == code).all()
        else:
            assert (counts[:, 0] == 131072 + round(7e-4 / m.lsb_t)).all()


def test_imu_saturation_is_reported_once_per_episode():
    """``Health.on_imu_saturated``: the first clipped IMU sample raises EVT_SATURATION with
    detail ``node | IMU_SATURATION`` (bit 8: not the magnetometer's, whose detail is the node
    alone); the next ones within ``saturation_quiet_us`` (1 s) of the one before are the same
    episode (a 3 s stretch clipped at 100 Hz: one event, 300 samples counted); a clip 1.2 s after
    the last starts a new one. An IMU of a node outside the sensors (the source's) is reported
    too. Catches an event per sample
    (300), none at all, or an IMU clip reported as the magnetometer's."""
    from coiltrack.firmware.supervise.health import IMU_SATURATION, Health
    from coiltrack.protocol.schema import EVT_SATURATION

    h = Health([16], 1, 100.0)
    got = []
    for t in range(1_000_000, 4_000_000, 10_000):
        h.on_imu_saturated(16, t)
    h.on_imu_saturated(16, 3_990_000 + 1_200_000)
    h.on_imu_saturated(40, 5_500_000)           # the source's IMU
    h.on_imu_saturated(40, 5_600_000)
    h.flush_events(lambda code, detail: got.append((code, detail)))
    assert IMU_SATURATION == 1 << 8
    assert got == [(EVT_SATURATION, 16 | IMU_SATURATION)] * 2 + [(EVT_SATURATION, 40 | IMU_SATURATION)]
    assert h.imu_saturated_samples == 300 + 1 + 2 and h.imu_saturation_events == 3
    assert h.saturation_events == 0             # the magnetometer's count is its own
