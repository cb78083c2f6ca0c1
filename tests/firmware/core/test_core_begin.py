"""A burst's solve inputs at its begin on the compiled core (firmware_py/core/src/begin.c:
ct_begin_inputs, ct_input_status, ct_prepare_currents; glue py_begin.c ``BurstInputs``) against the
Python reference (``SensorChannel.burst_flags``, ``PulseSchedule.any_faults``,
``track.status.input_status``, the usable test of ``MagneticTracker._begin`` and
``MagneticTracker._prepare_currents``), on seeded flags, faults and currents: every bit equal, every
current equal to the bit. Skips where the extension is not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_UNUSABLE
from coiltrack.firmware.track.magnetic import MagneticTracker
from coiltrack.firmware.track.status import COIL_FATAL, input_status
from coiltrack.protocol.schema import POSE_COIL_FAULT, POSE_DEGRADED, POSE_SATURATED

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
BITS = (PULSE_SATURATED, PULSE_UNUSABLE, COIL_FATAL, POSE_SATURATED, POSE_DEGRADED, POSE_COIL_FAULT)


def _reference(fl, fv):
    flags = 0
    for f in fl:
        flags |= int(f)
    faults = 0
    for f in fv:
        faults |= int(f)
    return input_status(flags, faults), bool(flags & PULSE_UNUSABLE or faults & COIL_FATAL), flags


def test_status_matches_the_reference():
    """Flags drawn from every single bit, none, and mixtures (a saturated window, an unusable one,
    a fatal and a harmless fault): the bits, the usable test and the or of the flags equal."""
    rng = np.random.default_rng(11)
    n, nch = 3, 4
    flags = [np.zeros(n, dtype=np.int64) for _ in range(nch)]
    faults = np.zeros(n, dtype=np.int64)
    cur = np.zeros(n)
    k = _core.BurstInputs(tuple(flags), faults, np.zeros(n), np.ones(n), cur, BITS)
    seen = set()
    for trial in range(600):
        for f in flags:
            f[:] = [0 if rng.random() < 0.6 else 1 << int(rng.integers(0, 8)) for _ in range(n)]
        faults[:] = [0 if rng.random() < 0.7 else 1 << int(rng.integers(0, 6)) for _ in range(n)]
        for c in range(nch):
            want = _reference(flags[c], faults)
            r = k.status(c)
            assert (r & 255, bool(r & 256), r >> 9) == want, (trial, c)
            seen.add((want[0], want[1]))
    assert any(u for _, u in seen) and any(not u for _, u in seen)
    assert {b & POSE_SATURATED for b, _ in seen} == {0, POSE_SATURATED}
    assert {b & POSE_COIL_FAULT for b, _ in seen} == {0, POSE_COIL_FAULT}
    with pytest.raises(IndexError):
        k.status(nch)


def test_currents_match_the_reference():
    """The measured current where the driver reported one (non-zero, a negative one too), else the
    nominal: equal to ``_prepare_currents`` to the bit."""
    rng = np.random.default_rng(12)
    n = 5
    measured = np.zeros(n)
    nominal = rng.normal(size=n)
    cur = np.zeros(n)
    k = _core.BurstInputs((np.zeros(n, dtype=np.int64),), np.zeros(n, dtype=np.int64), measured, nominal, cur, BITS)

    class _T:
        _measv, _nomv = memoryview(measured), memoryview(nominal)
    for trial in range(50):
        measured[:] = np.where(rng.random(n) < 0.4, 0.0, rng.normal(size=n))
        want = np.zeros(n)
        MagneticTracker._prepare_currents(_T(), memoryview(want))
        k.currents()
        assert cur.tobytes() == want.tobytes(), trial


def test_bound_on_the_fused_tracker_and_refused_arrays():
    """The compiled firmware's tracker runs the compiled begin; arrays of another kind are refused
    at binding with a message naming them."""
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.port import Port

    class _Null(Port):
        def read(self) -> bytes:
            return b""

        def write(self, data: bytes) -> None:
            pass
    fw = Firmware(FirmwareConfig(), _Null())
    if fw.core == "compiled":
        tr = fw.tracker
        assert tr._begin.__func__ is not MagneticTracker._begin
    with pytest.raises(TypeError, match="faults"):
        _core.BurstInputs((np.zeros(3, dtype=np.int64),), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), BITS)
    with pytest.raises(ValueError, match="differ"):
        _core.BurstInputs((np.zeros(3, dtype=np.int64), np.zeros(2, dtype=np.int64)), np.zeros(3, dtype=np.int64),
                          np.zeros(3), np.zeros(3), np.zeros(3), BITS)


def _fused_firmware():
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.port import Port

    class _Null(Port):
        def read(self) -> bytes:
            return b""

        def write(self, data: bytes) -> None:
            pass
    return Firmware(FirmwareConfig(), _Null())


def test_solve_start_matches_the_reference():
    """``SolveStart.start`` (``ct_solve_start``: the sigmas, the fused tracker's warm start and the
    solve's begin in one call) against ``MagneticTracker._start_solve`` on a second, identically
    filled tracker: over random variances (some below the floor, a NaN), tracked poses had or not,
    histories reaching t_ref or not, filters initialised or not, poses beyond the working range,
    every sigma, start, the solver's loaded inputs, state and status equal to the bit."""
    ref, got = _fused_firmware().tracker, _fused_firmware().tracker
    if got._start_solve.__func__ is MagneticTracker._start_solve:
        pytest.skip("the compiled start is not bound (Python core)")
    assert ref._start_solve.__func__ is not MagneticTracker._start_solve
    ref._start_solve = MagneticTracker._start_solve.__get__(ref)
    rng = np.random.default_rng(21)
    warm_seen = set()
    for trial in range(80):
        t = np.cumsum(rng.integers(900, 1100, size=30)) + 10_000
        rows = rng.normal(size=(30, 12)) * 0.01
        rows[:, 0:3] += [0.2, 0.1, 0.15] if trial % 9 else [3.0, 0.0, 0.0]        # every 9th: out of range
        var = rng.uniform(0, 2e-18, size=(3, 3))
        var[0, 0] = np.nan if trial % 10 == 1 else var[0, 0]
        S = rng.normal(size=(3, 3)) * 1e-6
        have = trial % 6 != 0
        t_ref = int(t[15]) if trial % 7 else int(t[-1]) + 10
        for tr in (ref, got):
            ch = tr.channels[0]
            ins = tr.inertial[ch.node]
            live = ins.fusion.history.live
            live.clear()
            for k in range(30):
                live.d[live.push(int(t[k]))] = rows[k]
            ins.fusion.initialized = trial % 5 != 2
            ins.t_ref = t_ref
            np.copyto(ch.var, var)
            np.copyto(ch.S, S)
            tp = tr.poses[ch.node]
            tp.have_pose = have
            tp.position[:] = [0.21, 0.09, 0.16]
            tp.rotation[:] = np.eye(3)
            tr.currents[:] = [1.0, -1.5, 2.0]
            tr._next = 0
            tr._start_solve(ch)
        a, b = ref.solver, got.solver
        ca, cb = ref.channels[0], got.channels[0]
        pa, pb = ref.poses[ca.node], got.poses[cb.node]
        assert ca.sigma.tobytes() == cb.sigma.tobytes(), trial
        assert (pa.warm_p.tobytes(), pa.warm_R.tobytes()) == (pb.warm_p.tobytes(), pb.warm_R.tobytes()), trial
        assert (a.status, a._warm, a.next_unit is None, a.next_cost) == (b.status, b._warm, b.next_unit is None,
                                                                          b.next_cost), trial
        assert a._svst.tobytes() == b._svst.tobytes() and a._fit.p.tobytes() == b._fit.p.tobytes(), trial
        assert a._fit.R.tobytes() == b._fit.R.tobytes() and a._S.tobytes() == b._S.tobytes(), trial
        assert a._w.tobytes() == b._w.tobytes() and a._cur.tobytes() == b._cur.tobytes(), trial
        warm_seen.add(a._warm)
    assert warm_seen == {True, False}
