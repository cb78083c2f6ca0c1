"""The compiled pulse command and duty check of the single-coil mode (firmware_py/core/src/sc_policy.c
``ct_pulse_cmd_frame``, ``ct_scp_duty_ok``; glue in py_single_coil.c) against their references:
``protocol.framing.encode_frame`` of a ``COIL_PULSE_CMD`` (the independent reference: the
protocol's own encoder, struct.pack and its CRC) byte for byte, and
``actuate.single_coil_pulses.PulseBook.duty_ok`` on the Python core (integer sums and one
comparison: the same answer). Seeded; skips where the extension is not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.schedule import PulseSchedule
from coiltrack.firmware.actuate.single_coil_pulses import DUTY_HIST, PulseBook
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol import MSG
from coiltrack.protocol.framing import encode_frame

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
EXT = COMPILED.ext
PCMD = MSG["COIL_PULSE_CMD"]


def test_pulse_command_frame_is_the_encoders():
    """Random commands, the fields' extremes included (coil 255, pulse_id 65535, current +-32767 and
    -32768, start 0 and 2^64-1, duration 2^32-1), every sequence number and source: the same bytes
    as ``encode_frame``. Catches a field swapped or written big endian, the current's sign lost, a
    wrong CRC extra or COBS run."""
    rng = np.random.default_rng(30)
    cases = [(255, 65535, 32767, (1 << 64) - 1, (1 << 32) - 1), (0, 0, -32768, 0, 0), (1, 4095, -1, 8, 60_000)]
    for _ in range(400):
        cases.append((int(rng.integers(0, 256)), int(rng.integers(0, 65536)), int(rng.integers(-32768, 32768)),
                      int(rng.integers(0, 1 << 40)) * 8, int(rng.integers(0, 1 << 32))))
    for k, (coil, pid, ma, start, length) in enumerate(cases):
        seq, src = k % 256, (7 * k) % 256
        want = encode_frame(PCMD(coil, pid, ma, start, length), seq, src)
        assert EXT.pulse_cmd_frame(seq, src, coil, pid, ma, start, length) == want, (coil, pid, ma, start, length)


def test_pulse_command_frame_refuses_what_struct_pack_refuses():
    """A field out of its range gives None (the transmitter counts a tx error, as on struct.pack's
    refusal); a non-integer sequence is a TypeError."""
    for bad in [(256, 1, 0, 0, 1), (-1, 1, 0, 0, 1), (1, 65536, 0, 0, 1), (1, 1, 32768, 0, 1), (1, 1, -32769, 0, 1),
                (1, 1, 0, -8, 1), (1, 1, 0, 0, 1 << 32), (1, 1, 0, 0, -1), (1, 1, 0, 1 << 64, 1)]:
        with pytest.raises(Exception):
            encode_frame(PCMD(*bad), 0, 1)
        assert EXT.pulse_cmd_frame(0, 1, *bad) is None, bad
    with pytest.raises(TypeError):
        EXT.pulse_cmd_frame(0.5, 1, 1, 1, 0, 0, 1)


class _Port:
    def __init__(self):
        self.frames = []

    def write(self, frame):
        self.frames.append(bytes(frame))


def test_schedule_sends_the_same_bytes_on_both_cores():
    """``PulseSchedule.command`` through the compiled transmitter (``Transmitter.coil_pulse``) and the
    Python one, interleaved with other frames (events, windows) and a command out of range: the same
    byte stream, the same sequence numbers and tx errors, the same returned ids and currents."""
    out = {}
    for impl in ("python", "compiled"):
        c = core.load(impl)
        port = _Port()
        tx = Transmitter(port, 1, 100_000, None, core=c)
        assert tx.core == impl
        sched = PulseSchedule(3, tx, [2.0, 2.5, 3.0])
        rng = np.random.default_rng(5)
        got = []
        for k in range(60):
            tx.begin_tick(k * 1000)
            coil = int(rng.integers(0, 3))
            cur = float(rng.uniform(-1.2, 1.2))
            got.append(sched.command(coil, cur, 1000 * k + int(rng.integers(0, 50_000)), int(rng.integers(1, 90_000))))
            if k % 7 == 3:
                tx.event(3, k)
            if k % 11 == 5:
                tx.pulse_window(2, coil, k, 10 * k, 10 * k + 5, 4, 3, 0)
            if k == 20:
                got.append(sched.command(coil, cur, 1000, 1 << 33))          # duration beyond u32: a tx error
        out[impl] = (port.frames, got, tx.tx_errors, sched.energy_j, sched.pulses)
    assert out["python"][2] == 1
    assert out["compiled"] == out["python"]


def _book(impl):
    cfg = FirmwareConfig()
    sched = type("S", (), {"command": staticmethod(lambda coil, current, start, length: (1, current))})()
    return cfg, PulseBook(cfg, 3, sched, (), 30_000, 20_000, 0, core.load(impl))


def test_duty_check_compiled_is_the_reference():
    """``PulseBook.duty_ok`` on the compiled core (``DutyCore.ok``) against the Python method on the same
    pulse trains: random trains longer than the history, pulses straddling the window's start, and
    asked lengths that put the on-time exactly at the bound (an off-by-one in the comparison or a
    rounded bound flips those)."""
    cfg, _ = _book("python")
    window = cfg.limits.coil_duty_window_us
    bound = cfg.adaptive.duty_margin * cfg.limits.coil_max_duty * window
    rng = np.random.default_rng(31)
    seen = set()
    for trial in range(40):
        books = [_book(impl)[1] for impl in ("python", "compiled")]
        assert books[1].duty_ok != books[0].duty_ok
        t = 0
        for _ in range(int(rng.integers(1, 3 * DUTY_HIST))):
            c = int(rng.integers(3))
            length = int(rng.integers(20_000, 90_000))
            t += int(rng.integers(0, 60_000))
            for b in books:
                b.release(b.slots[b.command(c, 0.5, t, length, True)])
            t += length
        for _ in range(20):
            c = int(rng.integers(3))
            start = t + int(rng.integers(-100_000, 400_000))
            length = int(rng.integers(1, 200_000))
            want = PulseBook.duty_ok(books[0], c, start, length)
            assert books[1].duty_ok(c, start, length) == want
            seen.add(want)
        # the length that brings the on-time to the bound exactly (integer bound), and one more
        c = int(rng.integers(3))
        start = t + 10_000
        lo, hi = 1, window
        while lo < hi:                      # the longest length still allowed
            mid = (lo + hi + 1) // 2
            if PulseBook.duty_ok(books[0], c, start, mid):
                lo = mid
            else:
                hi = mid - 1
        for length in (lo, lo + 1):
            assert books[1].duty_ok(c, start, length) == PulseBook.duty_ok(books[0], c, start, length)
    assert seen == {True, False}
    assert float(bound).is_integer()


def test_duty_core_refuses_bad_binding():
    """The history must be the book's int64 array of the stated size; a coil out of range is refused."""
    hist = np.zeros((3, DUTY_HIST, 2), dtype=np.int64)
    with pytest.raises(TypeError):
        EXT.DutyCore(hist.astype(float), 3, DUTY_HIST, 1_200_000, 570_000.0)
    with pytest.raises((TypeError, ValueError)):
        EXT.DutyCore(hist, 4, DUTY_HIST, 1_200_000, 570_000.0)
    d = EXT.DutyCore(hist, 3, DUTY_HIST, 1_200_000, 570_000.0)
    assert d.ok(2, 0, 570_000) and not d.ok(2, 0, 570_001)
    with pytest.raises(ValueError):
        d.ok(3, 0, 1)


def test_when_to_pulse_compiled_is_the_reference_bit_for_bit():
    """``CompiledActuationPolicy`` (``ct_scp_policy_*``) against ``coil_choice.ActuationPolicy`` on random
    predicted covariances and bounds, per variable and on the traces: ``worst`` and ``var_max`` equal
    with ``==``, ``due`` and ``reason`` the same, a NaN variance due, a bound not above 0 taken as
    1e-24, the interval's edge (``now - last == max_interval``) due. Independent reference for
    ``worst``: ``sqrt(max(diag(P6) / sigma_max^2))`` through numpy. Catches a square root taken per
    ratio, a trace summed in another order, or ``<`` for ``>=`` at the interval."""
    from coiltrack.firmware.actuate.coil_choice import ActuationPolicy
    from coiltrack.firmware.actuate.single_coil_policy import CompiledActuationPolicy, actuation_policy

    rng = np.random.default_rng(33)
    assert type(actuation_policy(core.load("python"), [1.0] * 6, 10, False)) is ActuationPolicy
    assert type(actuation_policy(COMPILED, [1.0] * 6, 10, False)) is CompiledActuationPolicy
    reasons = set()
    for trace in (False, True):
        smax = [2e-3] * 3 + [0.02] * 3
        ref, got = ActuationPolicy(smax, 400_000, trace), CompiledActuationPolicy(smax, 400_000, trace, EXT)
        for trial in range(300):
            b = np.exp(rng.uniform(np.log(1e-4), np.log(0.05), 6))
            if trial % 17 == 0:
                b[int(rng.integers(6))] = 0.0 if trial % 2 else -1.0
            A = rng.normal(size=(6, 6)) * np.exp(rng.uniform(np.log(1e-4), np.log(3e-2)))
            P6 = A @ A.T
            if trial % 29 == 0:
                P6[2, 2] = np.nan
            now, last = int(rng.integers(0, 2_000_000)), int(rng.integers(0, 2_000_000))
            if trial % 13 == 0:
                last = now - 400_000
            ref.set_bounds(b)
            got.set_bounds(b)
            assert np.array_equal(got.var_max, ref.var_max)
            assert got.due(P6, now, last) == ref.due(P6, now, last)
            assert got.reason == ref.reason
            reasons.add(ref.reason)
            w = ref.worst(P6)
            assert got.worst(P6) == w or (np.isnan(w) and np.isnan(got.worst(P6)))
            if not trace and not np.isnan(P6).any():
                vm = np.where(b > 0.0, b * b, 1e-24)
                assert got.worst(P6) == pytest.approx(float(np.sqrt(np.max(np.diag(P6) / vm))), rel=1e-15)
    assert reasons == {0, 1, 2}


def test_a_views_prediction_in_one_call_is_the_calls_it_replaces():
    """``ViewCore.predict`` (``AdaptiveActuation._predict_view_compiled``) against the calls of
    ``_predict_view`` on the compiled core one by one (the filter's orientation copied, ``predict_pose``
    over the horizon in 8 steps, ``BoundsCore.bounds``, the policy's ``set_bounds``), on a propagated
    filter, stated bounds scaled with the range and the NIS excess, horizons negative (none), zero and
    up to 0.3 s: every output equal with ``==``. A ``pp`` that is not the bounds core's is refused."""
    from coiltrack.firmware.actuate.single_coil_policy import CompiledActuationPolicy
    from coiltrack.firmware.estimate.single_coil import SchepersEKF

    cfg = FirmwareConfig()
    rng = np.random.default_rng(34)
    ekf = SchepersEKF.from_config(cfg, core=COMPILED)
    ekf.initialize(np.array([0.2, -0.1, 0.15]), np.eye(3), np.diag([4e-6] * 3 + [1e-4] * 3), 0, 0.05, 0.02, 0.003)
    for t in range(10_000, 200_000, 10_000):
        ekf.propagate(t, np.array([0.2, -0.1, 9.8]) + rng.normal(0, 0.05, 3), rng.normal(0, 0.4, 3))
    params = np.array([1.0, 0.5, 2.0, 1.0, 4.0, 0.5, 2.0, 2e-3, 1e-3, 1.0, 0.5, 0.3, 1.5, 1.0, 0.0, 0.0])
    outs = []
    for fused in (True, False):
        P6, pp, Rd, mx, mn = np.zeros((6, 6)), np.zeros(3), np.zeros((3, 3)), np.zeros(6), np.zeros(6)
        bd = EXT.BoundsCore((pp, mx, mn), None, None, params)
        pol = CompiledActuationPolicy([1e-3] * 6, 10 ** 6, False, EXT)
        vc = EXT.ViewCore(ekf._ck, bd, pol._ck, P6, pp, Rd)
        got = []
        for h, excess in ((-5_000, 1.0), (0, 2.5), (60_000, 1.0), (310_000, 7.0)):
            if fused:
                vc.predict(h, False, False, excess)
            else:
                np.copyto(Rd, ekf.R)
                ekf.predict_pose(h, P6, pp)
                bd.bounds(False, False, excess)
                pol.set_bounds(mx)
            got.append([a.copy() for a in (P6, pp, Rd, mx, mn, pol.var_max)])
        outs.append(got)
    for a, b in zip(*outs):
        for x, y in zip(a, b):
            assert np.array_equal(x, y)
    assert not np.array_equal(outs[0][0][0], outs[0][3][0])            # the horizon counts
    with pytest.raises(ValueError):
        EXT.ViewCore(ekf._ck, bd, pol._ck, np.zeros((6, 6)), np.zeros(3), np.zeros((3, 3)))
