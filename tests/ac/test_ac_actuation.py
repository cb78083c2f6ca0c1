"""The AC actuation stage: the plan on the wire, the driver's reports, a refused plan sent again."""
import pytest

from coiltrack.firmware.actuate.ac import ACActuation
from coiltrack.protocol import MSG
from coiltrack.protocol.schema import AC_FAULT_REFUSED
from coiltrack.tools.scenarios.ac import ac_config

Status = MSG["AC_DRIVE_STATUS"]


class _Tx:
    def __init__(self):
        self.sent, self.events = [], []

    def send(self, msg):
        self.sent.append(msg)

    def event(self, code, detail):
        self.events.append((code, detail))


def test_plan_sent_ahead_then_ready_with_the_measured_phasors():
    """One AC_DRIVE_CMD per coil ``ac_lead_us`` before ``boot + ac_start_us``, the reference at the
    switch-on, frequencies in mHz and the amplitude in uA; ready only when every coil reported:
    catches a plan sent late, a coil missing, or samples used before the phasors are known."""
    cfg = ac_config(fusion=False)
    tx = _Tx()
    act = ACActuation(cfg, tx)
    boot = 5_000
    act.step(boot)
    on = boot + cfg.ac.ac_start_us
    act.step(on - cfg.ac.ac_lead_us - 1000)
    assert tx.sent == []
    act.step(on - cfg.ac.ac_lead_us)
    assert [(m.coil, m.freq_mhz, m.amplitude_ua, m.ref_us, m.start_us) for m in tx.sent] == [
        (0, 215_000, 1_500_000, on, on), (1, 315_000, 1_500_000, on, on), (2, 465_000, 1_500_000, on, on)]
    pid = tx.sent[0].plan_id
    for c in range(2):
        act.on_status(Status(c, pid, tx.sent[c].freq_mhz, 1_499_000 + c, -1000 * (c + 1), on, 0))
    assert not act.ready
    act.on_status(Status(2, pid + 1, 465_000, 1_500_000, 0, on, 0))       # another plan's: ignored
    assert not act.ready
    act.on_status(Status(2, pid, 465_000, 1_500_000, 2500, on, 0))
    assert act.ready
    assert list(act.amplitude_a) == pytest.approx([1.499, 1.499001, 1.5])
    assert list(act.phase_rad) == pytest.approx([-1e-3, -2e-3, 2.5e-3])


def test_refused_plan_is_sent_again_later_with_a_new_id():
    """A refusal (the driver not yet synchronised) reports a coil fault and, ``ac_lead_us`` after
    the planned switch-on, a new plan with the next id and a switch-on ``ac_lead_us`` ahead:
    catches a firmware that waits for ever on a refused plan or reuses its id."""
    cfg = ac_config(fusion=False)
    tx = _Tx()
    act = ACActuation(cfg, tx)
    act.step(0)
    act.step(cfg.ac.ac_start_us - cfg.ac.ac_lead_us)
    first = tx.sent[:3]
    act.on_status(Status(0, first[0].plan_id, 215_000, 0, 0, first[0].ref_us, AC_FAULT_REFUSED))
    assert act.refusals == 1 and tx.events and not act.ready
    t = cfg.ac.ac_start_us + cfg.ac.ac_lead_us
    act.step(t)
    assert len(tx.sent) == 3
    act.step(t + 1000)
    second = tx.sent[3:]
    assert len(second) == 3 and {m.plan_id for m in second} == {first[0].plan_id + 1}
    assert second[0].start_us == t + 1000 + cfg.ac.ac_lead_us == second[0].ref_us
