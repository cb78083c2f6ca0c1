"""The reports of a burst's sensors in a loop on the compiled core (``MagneticTracker`` bound with
``_HandOver._report_loop``: each sensor's POSE, then the next sensor's begin ``_hand_over`` whose
report is the loop's next turn) against the reference's recursion (``_report`` -> ``_begin`` ->
``_report``), on test_core_handover.py's seeded multi16 states (a solve ahead finished, missed,
running; unusable and vetoed bursts; up to nine hand-overs in one call). ``test_core_handover``
compares the bits, counters and frames; here what a recorder sees: a ``_report`` or an
``on_solution`` set on the instance after the binding is called for every sensor of the chain, in
the reference's order. Skipped without the extension."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware.track.magnetic import _HandOver  # noqa: E402

_spec = importlib.util.spec_from_file_location("_handover", Path(__file__).with_name("test_core_handover.py"))
_ho = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_ho)              # its pair of firmwares, seeded states and comparison


def _recorded(fw, what: str) -> list:
    """The (node, solved) of every call of the tracker's ``what`` (``_report`` or ``on_solution``),
    through a recorder set on the instance."""
    tr = fw.tracker
    real = getattr(tr, what)
    calls = []

    def record(ch, solved):
        calls.append((ch.node, bool(solved)))
        real(ch, solved)
    setattr(tr, what, record)
    return calls


@pytest.mark.parametrize("what", ["_report", "on_solution"])
def test_a_recorder_set_on_the_instance_sees_every_sensor_of_the_chain(what):
    """Catches a loop that runs on past a ``_report`` wrapped since the binding (the chained
    sensors' reports unseen) or calls the ``on_solution`` bound at composition instead of the one
    set on the instance (a fusion's pending update not recorded): the calls, frames and bits equal
    the reference's, one call per POSE sent."""
    got, ref = _ho._pair()
    assert got.tracker._report.__func__ is _HandOver._report_loop
    seen = {fw: _recorded(fw, what) for fw in (got, ref)}
    sent = 0
    for seed in range(40):
        for fw in (got, ref):
            _ho._setup(fw, 9000 + seed)
        got.tracker._begin(got.tracker.channels[0])
        ref.tracker._begin(ref.tracker.channels[0])
        _ho._same(got, ref)
        sent += len(got.port.out)
    assert seen[got] == seen[ref]
    assert len(seen[got]) == sent > 100                     # (each call sent one POSE)
    assert any(not s for _, s in seen[got]) and sum(s for _, s in seen[got]) > 60


def test_the_reports_initialised_flag_is_the_fusion_filters():
    """The compiled report reads each sensor's fusion filter's ``initialized`` through a view of
    its ``fs`` (``_initialized_flag``): catches the view of another entry or another sensor's filter
    (a pose graded as if the filter were initialised)."""
    got, _ = _ho._pair()
    tr = got.tracker
    for ch in tr.channels:
        chain, cov, fus, frame, init = tr._chains[ch.node]
        assert fus is tr.inertial[ch.node].fusion and init is not None
        for v in (True, False, True):
            fus.initialized = v
            assert (init[0] != 0) is v
            assert np.count_nonzero(fus.fs) == int(v)


def test_the_reports_frame_is_numbered_and_counted_as_write_numbered():
    """``ReportChain.send`` (``Transmitter._pose_built_compiled``'s one call) against
    ``Transmitter._write_numbered``: the sequence wraps at 256, a write that raises an Exception is
    one error with the sequence counted on, a value the wire format refuses (a quality of 256) is
    one error with nothing written and the sequence kept, and a KeyboardInterrupt is not swallowed.
    Catches a sequence not masked, counted on for a refused frame or not for a failed write, and a
    link's failure that stops the loop."""
    got, _ = _ho._pair()
    tr = got.tracker
    _ho._setup(got, 9000)
    tr._begin(tr.channels[0])                  # reports: the chains hold a pose
    send = tr._chains[tr.channels[0].node][3]
    out = []
    assert send(out.append, 255, 1, 16, 10_000, 1, 200) == 0 and len(out) == 1
    assert send(out.append, 7, 1, 16, 10_000, 1, 256) == (1 << 8) | 7 and len(out) == 1

    def fail(frame, exc=ValueError):
        out.append(frame)
        raise exc("link full")
    assert send(fail, 9, 1, 16, 10_000, 1, 200) == (1 << 8) | 10 and len(out) == 2
    assert out[1][:1] == out[0][:1] and out[1] != out[0]       # (numbered 9, not 255)
    with pytest.raises(KeyboardInterrupt):
        send(lambda f: fail(f, KeyboardInterrupt), 9, 1, 16, 10_000, 1, 200)
