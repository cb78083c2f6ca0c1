"""The receive stage's compiled route (firmware_py/core/src/rxdecode.c ``ct_rx_step``, ``ct_rx_route``;
glue ``RxRoute``) against its reference, the whole receive stage on the Python core: a receiver with
the protocol's ``FrameDecoder``, Python supervisor and Python sensor channels, and one with the
compiled decoder, the supervisor's kernels and compiled channels, whose route decodes and routes the
magnetometer rows in C and hands every other row back in order.

A seeded stream of every message: MAG_PACKED and MAG_SAMPLE of the sensors (stamps on the sample
grid, jittered past the supervisor's tolerance, duplicated, from the future, saturated, set/reset
flips), of a node that is no channel (the tracker's) and of the coil driver, IMU samples (some
clipped, some of a node the supervisor has lost: the supervisor's part of the others done by the
route), coil status, heartbeats, sync replies and corrupt bytes; reads cut at random, some longer
than the decoder's table of rows (the route resumes the decode). After every tick both stages' whole
state must be equal: every channel's ring bit for bit (times, fields, flags, head, count, latest,
refusals, counters), the supervisor's state (its floats bit for bit), what the tracker and the
other handler were handed, and the counters. Seeded; skips without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.windows import SensorChannel
from coiltrack.firmware.receive import Receiver
from coiltrack.firmware.rxdecode import ROWS, RX_NEW, RX_OVER_LIMIT, RX_RESUME, RX_TAKEN, CompiledFrameDecoder
from coiltrack.firmware.supervise.supervisor import Supervisor
from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.schema import IMU_CLIP_COUNTS, MAG_LSB_T, STAMP_FLIP, STAMP_SATURATED, pack_stamp

ext = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from .test_core_rxdecode import _Port, _Sink  # noqa: E402  (after the skip: that module skips too)
from .test_core_sample_push import _same
from .test_core_supervise import _Schedule, _Tx, _floats_bitwise, _state

COMPILED = core.load("compiled")
SENSORS = (16, 17, 18, 40)
OTHER = 99                   # a magnetometer that is no sensor channel: the tracker's


class _Sched(_Schedule):
    def __init__(self, n, log):
        super().__init__(n)
        self.log = log

    def on_status(self, msg):
        self.log.append(("status", tuple(msg)))


def _stage(c, cfg, limit):
    sink = _Sink()
    sched = _Sched(len(cfg.source.coils), sink.log)
    chans = tuple(SensorChannel(n, cfg, c) for n in SENSORS)
    sup = Supervisor(cfg, sched, _Tx())
    dec = FrameDecoder() if c.ext is None else CompiledFrameDecoder(c.ext)
    r = Receiver(_Port(), dec, chans, sched, sink, sup, _Tx(), other=sink.other, core=c, frames_per_tick=limit)
    return r, sink, sched, chans, sup


def _imu(rng, node, now):
    v = [int(x) for x in rng.integers(-30000, 30000, 6)]
    if rng.random() < 0.2:
        v[int(rng.integers(6))] = IMU_CLIP_COUNTS
    return encode_frame(MSG["IMU_SAMPLE"](node, now - 500, *v), 0, 1)


def _frames(rng, cfg, now, t, seq, silent, back):
    """One tick's frames (the sensors' samples due by ``now`` and the rarer messages), ``t`` the
    nodes' next sample times (advanced here); node ``silent`` sends nothing, node ``back`` an IMU
    sample first."""
    P = 1e6 / cfg.pulse.mag_rate_hz
    out = b"" if back is None else _imu(rng, back, now)
    for node in SENSORS + (OTHER, cfg.link.coil_driver_id):
        while node == silent and t[node] <= now:
            t[node] += int(P)
        while t[node] <= now:
            s = t[node] + int(rng.choice([0, 0, 0, 0, 0, 0, 0, 0, 400, -2 * int(P), 30_000]))
            x, y, z = (int(v) for v in rng.integers(-8000, 8000, 3) + np.array([6000, 0, 8000]))
            flip = int(rng.random() < 0.3) | (2 if rng.random() < 0.01 else 0)
            if rng.random() < 0.85:
                msg = MSG["MAG_PACKED"](node, x, y, z, pack_stamp(s) | (STAMP_FLIP if flip & 1 else 0)
                                        | (STAMP_SATURATED if flip & 2 else 0))
            else:
                msg = MSG["MAG_SAMPLE"](node, s, x, y, z, flip)
            out += encode_frame(msg, seq[0] & 0xFF, node)
            seq[0] += 1
            t[node] += int(P) if rng.random() > 0.02 else 3 * int(P)
    r = rng.random()
    if r < 0.3:
        out += _imu(rng, int(rng.choice([n for n in SENSORS + (OTHER,) if n != silent])), now)
    elif r < 0.33:
        out += encode_frame(MSG["COIL_STATUS"](int(rng.integers(3)), 0, 1000, now - 3000, now - 1000,
                                               int(rng.choice([0, 0, 4]))), 0, 2)
    elif r < 0.35:
        out += encode_frame(MSG["HEARTBEAT"](SENSORS[0], 1, 0, 1, 0, 0), 0, 3)
    elif r < 0.38:
        out += encode_frame(MSG["TIME_SYNC_REPLY"](SENSORS[1], 7, now + 300, 300, 10), 0, 4)
    elif r < 0.40 and out:
        i = int(rng.integers(len(out)))
        out = out[:i] + bytes([out[i] ^ 0x40]) + out[i + 1:]     # a corrupt frame (CRC or COBS)
    return out


@pytest.mark.parametrize("limit", [0, 6])
def test_the_compiled_route_keeps_the_whole_receive_stage_of_the_reference(limit):
    """With and without a frame limit per tick (``rx_frames_per_tick``: the route counts a read's
    frames against it, the reference's ``_take`` cuts it). Catches a sample's field pushed as another
    (x for y, the time for the stamp), the saturated and set/reset bits swapped, the supervisor's kernel skipped or a handed-back sample pushed twice,
    the packed count missed, an IMU sample's supervisor part done twice or not at all (a lost node's
    return), a row routed out of order with the ones handed back, the rows past a
    full table of ROWS lost (the decode not resumed), a node that is no channel pushed anyway."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": SENSORS}).validate()
    ref, rs, rsched, rch, rsup = _stage(core.PYTHON, cfg, limit)
    got, gs, gsched, gch, gsup = _stage(COMPILED, cfg, limit)
    assert isinstance(got.decoder, CompiledFrameDecoder) and gsup.pose_kernel() is not None
    handed = [0]
    rows_from = got._rows_from

    def counting(k, data, now):
        handed[0] += 1
        rows_from(k, data, now)
    got._rows_from = counting
    rng = np.random.default_rng(11)
    now = 2_000_000
    t = {n: now - int(rng.integers(0, 8000)) for n in SENSORS + (OTHER, cfg.link.coil_driver_id)}
    seq, held, longest = [0], b"", 0
    for k in range(1500):
        now += int(rng.choice([1000, 7000, 40_000, 150_000], p=[0.6, 0.2, 0.18, 0.02]))
        if k % 200 == 0:                                  # the pulses move over the stamps
            for sched in (rsched, gsched):
                sched.start[:] = now + 4000 * np.arange(len(sched.start)) - 10_000
                sched.end[:] = sched.start + 2000
        quiet = 300 <= k % 500 <= 450                    # the last sensor silent (lost), then back: an
        held += _frames(rng, cfg, now, t, seq, SENSORS[-1] if quiet else None,     # IMU sample its only frame
                        SENSORS[-1] if k % 500 == 450 else None)
        if rng.random() < 0.03:
            continue                                       # a read late: the next one is long
        cut = len(held) if rng.random() < 0.8 else int(rng.integers(len(held) + 1))
        data, held = held[:cut], held[cut:]
        longest = max(longest, data.count(b"\x00"))
        ref.port.data = got.port.data = data
        ref.step(now)
        got.step(now)
        rsup.health.step(now)
        gsup.health.step(now)
        assert gs.log == rs.log, k
        for a, b in zip(rch, gch):
            _same(a, b, k)
        sa, sb = _state(rsup), _state(gsup)
        assert sa == sb, k
        _floats_bitwise(sa, sb)
        assert got.counters() == ref.counters(), k
    c = ref.counters()
    assert c["rx_mag_packed"] > 2500 and c["rx_crc_errors"] + c["rx_framing_errors"] > 5
    assert longest > ROWS if not limit else c["rx_deferred"] > 1000
    assert {e[0] for e in rs.log} >= {"mag", "imu", "status", "coil", "other"}
    assert rsup.health.saturation_events and rsup.health.clock_steps and rsup.health.back_events >= 3
    # most magnetometer rows routed in C; the rare ones and every other message handed back
    assert 250 < handed[0] < c["rx_frames_ok"] / 4


def test_route_refuses_a_table_it_does_not_hold():
    """The glue's checks: a channel index beyond the channels bound, a resume whose state points
    outside the decoder's table and an unknown mode raise instead of reading out of bounds; the frame
    limit's edge (a read of exactly the limit is cut, one frame fewer is not). Catches the limit
    compared with > where the reference's ``count >= frames_per_tick`` is meant."""
    dec = CompiledFrameDecoder(ext)
    st = np.zeros(ext.RXS_N, dtype=np.int64)
    nodes = np.full(256, -1, dtype=np.int64)
    nodes[3] = 0
    with pytest.raises(ValueError):
        dec.route_kernel(None, nodes, (), st, MAG_LSB_T)
    step = dec.route_kernel(None, np.full(256, -1, dtype=np.int64), (), st, MAG_LSB_T, 2).step
    st[0], st[1] = ROWS + 1, 0
    with pytest.raises(ValueError):
        step(b"\x00", RX_RESUME, 0)
    with pytest.raises(ValueError):
        step(b"", 3, 0)
    assert step(b"", RX_NEW, 0) == -1
    # the frame limit (2): one frame decoded, two not (nothing counted), two taken decoded
    assert step(b"\x01\x00", RX_NEW, 0) == -1 and dec.bytes_in == 2
    assert step(b"\x01\x00\x01\x00", RX_NEW, 0) == RX_OVER_LIMIT and dec.bytes_in == 2
    assert step(b"\x01\x00\x01\x00", RX_TAKEN, 0) == -1 and dec.bytes_in == 6
