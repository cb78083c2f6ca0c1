"""A solve ahead's begin and its take-over on the compiled core (firmware_py/core/src/begin.c
``ct_ahead_start``, ``ct_begin_ahead``, ``ct_ahead_inputs``; py_begin.c ``AheadStart``) against their
Python references, ``MagneticTracker._ahead_start`` (``warm_start``, ``_begin_ahead``) and
``MagneticTracker._start_solve`` (``fill_sigma``, ``warm_start``, ``_use_ahead``).

Two multi16 firmwares built alike are given the same seeded random state: channels' signals and
variances, sample rings around the last window (some with no sample inside it, some without a
baseline), tracked poses had or not, fusion filters initialised or not, measured currents or the
nominal; one runs the compiled call, the other the reference. Everything either writes is compared
bit for bit: the solves ahead's copies and extractions, the warm starts, the sigmas, the solver's
loaded inputs and state, the answer, the counters and, for the take-over, the POSE frames sent. A
wrong column replaced, a sigma not floored, a current not taken from the driver, a hemisphere or a
start taken from the wrong array, a comparison that misses an input, a cold start taken for a
warm one or the reverse, or an acquisition begun ahead from the tracked position instead of the
sensor's hemisphere changes a figure or a decision here. Seeded; skipped without the extension."""
import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware.estimate.magnetic_inertial import FS_INIT  # noqa: E402
from coiltrack.firmware.loop import Firmware  # noqa: E402
from coiltrack.firmware.track.magnetic import MagneticTracker  # noqa: E402
from coiltrack.tools import scenarios  # noqa: E402

START, END = 1_000_000, 1_050_000          # the last window (coil n - 1)


class _Port:
    def __init__(self):
        self.out = []

    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        self.out.append(bytes(data))


def _pair():
    cfg = scenarios.get("multi16").firmware_config().with_(core={"impl": "compiled"}).validate()
    got, ref = Firmware(cfg, _Port()), Firmware(cfg, _Port())
    assert got.tracker._ahead_start.__func__ is MagneticTracker._ahead_start_compiled
    assert got.tracker._as_inputs is not None
    del ref.tracker._ahead_start              # the references
    ref.tracker._as_inputs = None
    return got, ref


@pytest.fixture(scope="module")
def pair():
    return _pair()


def _rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _fill_ring(ring, rng, case):
    """Samples every 7-9 ms around the window; ``case`` 1: none inside it, 2: none after it."""
    ring.clear()
    t = START - 50_000 + int(rng.integers(0, 9000))
    stop = END + 3000 + 35_000 + 20_000 if case != 2 else END - 1000
    base = rng.normal(0.0, 3e-5, 3)
    amp = rng.normal(0.0, 2e-6, 3)
    while t < stop:
        if not (case == 1 and START <= t <= END):
            b = base + rng.normal(0.0, 2e-8, 3) + (amp if START <= t <= END else 0.0)
            ring.push(t, b[0], b[1], b[2], bool(rng.random() < 0.01), 0)
        t += int(rng.integers(7000, 9001))


def _state(fw, seed: int) -> None:
    """The same random state into ``fw`` for the same ``seed``."""
    rng = np.random.default_rng(seed)
    tr = fw.tracker
    sch = tr.schedule
    n = sch.n
    sch.start[n - 1], sch.end[n - 1] = START, END
    sch.measured[:] = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(0.5, 2.0, n))
    tr._prepare_currents(tr._curv)
    for ch in tr.channels:
        ch.S[:] = rng.normal(0.0, 1e-6, ch.S.shape)
        ch.var[:] = np.where(rng.random(ch.var.shape) < 0.3, 0.0, rng.uniform(0.0, 1e-16, ch.var.shape))
        _fill_ring(ch.extractor._ring, rng, int(rng.choice([0, 0, 0, 1, 2])))
        tp = tr.poses[ch.node]
        d = rng.normal(size=3)
        tp.position[:] = d / np.linalg.norm(d) * rng.uniform(0.2, 0.4) * (3.0 if rng.random() < 0.05 else 1.0)
        tp.rotation[:] = _rotation(rng)
        tp.have_pose = bool(rng.random() < 0.85)
        tr.inertial[ch.node].fusion.fs[FS_INIT] = int(rng.random() < 0.2)


def _arrays(fw) -> dict:
    """Every float or int array the begin and the take-over may write, by name."""
    tr, sv = fw.tracker, fw.tracker.solver
    objs = {"sv": sv, "fit": sv._fit, "q": tr.quality}
    for k, ch in enumerate(tr.channels):
        objs.update({f"ah{k}": tr._ahead[k], f"tp{k}": tr.poses[ch.node], f"ch{k}": ch, f"x{k}": ch.extractor,
                     f"ins{k}": tr.inertial[ch.node]})
    out = {}
    for name, o in objs.items():
        for a, v in vars(o).items():
            if isinstance(v, np.ndarray):
                out[f"{name}.{a}"] = v.tobytes()
    out["ahead_st"] = tr._ahead_st.tobytes()
    return out


def _scalars(fw) -> tuple:
    tr, sv = fw.tracker, fw.tracker.solver
    nu = sv.next_unit
    return (tr._ahead_k, tr.ahead_solves, tr.ahead_used, tr.ahead_missed, tr._next, tr._handover, tr._status,
            sv.status, getattr(nu, "__name__", nu), sv.next_cost, sv.iterations, sv.cost, sv.solve_evals,
            tuple(tr.poses[ch.node].have_pose for ch in tr.channels), tr.out_of_range)


def _same(got, ref) -> None:
    a, b = _arrays(got), _arrays(ref)
    assert a.keys() == b.keys()
    bad = [k for k in a if a[k] != b[k]]
    assert not bad, bad
    assert _scalars(got) == _scalars(ref)
    assert got.port.out == ref.port.out


def test_the_begin_of_a_solve_ahead_equals_the_reference(pair):
    """300 random states: ``_ahead_start`` on the compiled core and the reference give the same
    answer and write the same bits (cold starts, acquiring ahead, windows with no pulse or no
    baseline samples, begins refused by the solver's checks and warm begins among them)."""
    got, ref = pair
    answers = set()
    for seed in range(300):
        for fw in (got, ref):
            _state(fw, seed)
        _same(got, ref)
        k = seed % 16
        r = got.tracker._ahead_start(k, START, END)
        assert r == ref.tracker._ahead_start(k, START, END)
        answers.add((r, got.tracker.channels[k].extractor._ires[1] == 0, got.tracker.poses[k + 16].have_pose))
        _same(got, ref)
    assert (True, False, True) in answers and (False, True, True) in answers and (True, False, False) in answers
    assert (False, True, False) in answers


def test_a_time_beyond_the_kernels_range_goes_to_the_reference(pair):
    """A window end beyond +-2^61 us (or not an int) is answered by the reference: the same answer
    and state as the reference's own call."""
    got, ref = pair
    for end in (1 << 62, float(END)):
        for fw in (got, ref):
            _state(fw, 7)
        r = got.tracker._ahead_start(3, START, end)
        assert r == ref.tracker._ahead_start(3, START, end)
        _same(got, ref)


def _ahead_of(fw, k: int, burst: int, change: int, running: bool) -> None:
    """Channel ``k``'s solve ahead for ``burst``, finished (or ``running``: begun, its steps to
    come), on the inputs its own solve will have (:meth:`MagneticTracker._start_solve`'s sigma and
    warm start, or acquiring from the hemisphere without one), one input changed where ``change``
    is 0..5 (its index in the six), its start's kind recorded as the other one where it is 6."""
    tr = fw.tracker
    ch = tr.channels[k]
    tp = tr.poses[ch.node]
    ah = tr._ahead[k]
    ch.fill_sigma()
    warm = tr.warm_start(ch, tp)
    for dst, src in zip((ah.S, ah.sigma, ah.currents, ah.hemisphere, ah.warm_p, ah.warm_R),
                        (ch.S, ch.sigma, tr.currents, tp.position if warm else tp.hemisphere, tp.warm_p, tp.warm_R)):
        np.copyto(dst, src)
    if 0 <= change < 6:
        a = (ah.S, ah.sigma, ah.currents, ah.hemisphere, ah.warm_p, ah.warm_R)[change]
        a.reshape(-1)[-1] = np.nextafter(a.reshape(-1)[-1], np.inf)
    ah.began(warm != (change == 6))
    start = (ah.warm_p, ah.warm_R) if warm else ()
    begun = tr.solver.begin(ah.S, ah.currents, ah.sigma, ah.hemisphere, *start) & 16
    ah.take(burst)
    if running and begun:
        tr._ahead_k = k
        return
    while begun and tr.solver.step(100) & 16:
        pass
    tr.solver.save(ah.result)
    ah.finish()
    ch.var *= 1.0                            # (the state the take-over starts from: sigma recomputed there)


def test_taking_over_a_finished_solve_ahead_equals_the_reference():
    """180 random states, warm and acquiring: a burst's start where its solve ahead finished on
    the same inputs (the pose reported from it), is still running on them (it goes on), or was
    begun on inputs one element apart in each of the six arrays in turn (solved again; for an
    acquisition the warm start's two are not its inputs: taken over), or recorded as of the
    other kind of start (solved again): ``_start_solve`` on the compiled core and the reference
    send the same frames and write the same bits, the solve's steps after it too."""
    got, ref = _pair()
    for seed in range(180):
        k = seed % 15
        change = (seed // 15) % 9 - 2         # -2, -1: the same inputs; 0..5: one changed; 6: the other kind
        for fw in (got, ref):
            _state(fw, 1000 + seed)
            tr = fw.tracker
            tr.schedule.burst_start = 123_456
            tr._next, tr._units, tr._ahead_k = k, tr.budget, -1
            _ahead_of(fw, k, 123_456, change, seed % 4 == 1)
            fw.port.out.clear()
        _same(got, ref)
        got.tracker._start_solve(got.tracker.channels[k])
        ref.tracker._start_solve(ref.tracker.channels[k])
        _same(got, ref)
        for fw in (got, ref):
            while fw.tracker.solver.next_unit is not None:
                fw.tracker.solver.step(100)
        _same(got, ref)
    tr = got.tracker
    assert tr.ahead_used > 40 and tr.ahead_missed > 20 and tr.poses[16].have_pose is not None
