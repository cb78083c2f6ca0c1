"""Bench mode: a commanded pulse seen in the sensor's samples inside the firmware's window.

Each rule is a function of the :class:`~coiltrack.protocol.conformance.session.Session`
(``s``); it adds its results to the session."""
from __future__ import annotations

import numpy as np

from ..schema import CURRENT_LSB_A, ROLE_COIL_DRIVER, ROLE_SENSOR
from .results import FAIL, PASS
from .session import Session


def bench_rules(s: Session, nodes: dict) -> None:
    drivers = [n for n in sorted(nodes) if nodes[n] == ROLE_COIL_DRIVER]
    sensors = [n for n in sorted(nodes) if nodes[n] == ROLE_SENSOR]
    if not drivers or not sensors:
        s.add("bench_pulse", FAIL, "bench mode needs a coil driver and a sensor on the link", None)
        return
    for sn in sensors:
        bench_pulse_rule(s, drivers[0], sn)


def bench_samples(s: Session, sn: int, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    rx = [r.msg for r in s.log if r.src == sn and r.msg.NAME == "MAG_SAMPLE" and lo <= r.msg.t_us <= hi]
    t = np.array([m.t_us for m in rx], dtype=np.int64)
    B = np.array([[m.x, m.y, m.z] for m in rx], dtype=float).reshape(-1, 3)
    flip = np.array([m.flip & 1 for m in rx], dtype=np.int64)
    return t, B, flip


def bench_pulse_rule(s: Session, d: int, sn: int) -> None:
    o = s.o
    rate = o.mag_rate_hz or 120.0
    P = 1e6 / rate
    dur = int(o.bench_pulse_ms * 1000)
    problems, rise, fall, amps = [], [-1e9, 1e9], [-1e9, 1e9], []
    for i in range(o.bench_pulses):
        # the start dithered against the sensor's sample grid by i / bench_pulses of a period,
        # so that the samples bracket the edges to P / bench_pulses over the pulses
        grid = [r.msg.t_us for r in s.log[-400:] if r.src == sn and r.msg.NAME == "MAG_SAMPLE"]
        earliest = s.master_us() + int(o.lead_ms * 1000)
        if grid:
            k = int(np.ceil((earliest - grid[-1]) / P))
            start = grid[-1] + int(round((k + i / o.bench_pulses) * P))
        else:
            start = earliest
        s.run_for(0.0)
        cmd, mark, _ = s.pulse(d, current_ma=o.bench_current_ma, duration_us=dur,
                               lead_us=start - s.master_us(), coil=i % o.bench_coils)
        st = s.await_status(d, cmd, mark, True)
        s.run_for(0.05)                         # the trailing quiet samples
        if st is None or st.msg.faults:
            problems.append(f"pulse {i}: " + ("no COIL_STATUS" if st is None else
                                              f"COIL_STATUS faults {st.msg.faults:#04x}"))
            continue
        t0, t1 = cmd.start_us, cmd.start_us + dur
        # quiet since the previous pulse's fall (earlier rules' pulses and this rule's)
        quiet_from = max((r.msg.end_us for r in s.log[:mark] if r.msg.NAME == "COIL_STATUS"
                          and r.msg.end_us < t0), default=t0 - 35_000) + o.fall_us
        lo = min(t0 - 35_000, quiet_from)
        t, B, flip = bench_samples(s, sn, lo, t1 + 38_000)
        pre = (t >= t0 - 35_000) & (t <= t0 - 2_000)
        post = t >= t1 + o.fall_us
        # the set/reset offset changes sign with the flip bit: one quiet baseline per flip state.
        # A node that flips every few samples can hold one state over the whole window and the other
        # over both quiet spans (a 60 ms window, a flip every 66.7 ms): that state's baseline is then
        # taken from its quiet samples before the pulse, back to the previous pulse's fall
        earlier = (t >= quiet_from) & (t <= t0 - 2_000)
        base = np.zeros_like(B)
        for f in (0, 1):
            q = (pre | post) & (flip == f)
            if not q.any():
                q = earlier & (flip == f)
            base[flip == f] = B[q].mean(axis=0) if q.any() else np.nan
        keep = ~np.isnan(base[:, 0])
        t, B, base, pre, post = t[keep], B[keep], base[keep], pre[keep], post[keep]
        win = (t >= t0 + o.settle_us) & (t <= t1 - o.guard_us)
        if pre.sum() < 2 or win.sum() < 2 or post.sum() < 1:
            problems.append(f"pulse {i}: {int(pre.sum())} quiet and {int(win.sum())} in-window samples")
            continue
        dB = np.linalg.norm(B - base, axis=1)
        A = float(np.median(dB[win]))
        noise = float(np.std(dB[pre])) + 1.0
        amps.append(A)
        if A < 10.0 * noise:
            problems.append(f"pulse {i}: no field in the window ({A:.0f} LSB against {noise:.0f} LSB of noise)")
            continue
        if np.any(np.abs(dB[win] - A) > 0.1 * A):
            problems.append(f"pulse {i}: the field is not flat over the window (the node applies it late "
                            f"or early?)")
        if np.any(dB[post] > 0.05 * A) or np.any(dB[pre] > 0.05 * A):
            problems.append(f"pulse {i}: field in the quiet samples around the pulse")
        on = dB > 0.5 * A
        rel = t - t0
        # the rise edge lies between the last sample off and the first sample on (relative to the start)
        first_on = int(np.argmax(on))
        if on[first_on] and first_on > 0:
            rise = [max(rise[0], rel[first_on - 1]), min(rise[1], rel[first_on])]
        last_on = len(on) - 1 - int(np.argmax(on[::-1]))
        if last_on + 1 < len(on):
            fall = [max(fall[0], rel[last_on] - dur), min(fall[1], rel[last_on + 1] - dur)]
    if problems:
        s.add("bench_pulse", FAIL, "; ".join(problems[:3]), sn)
        return
    detail = (f"{o.bench_pulses} pulses of {o.bench_current_ma * CURRENT_LSB_A:g} A for {dur} us on node {d}: "
              f"field {np.median(amps):.0f} LSB; rise edge at {rise[0]:+.0f}..{rise[1]:+.0f} us of the commanded "
              f"start (margin {o.settle_us - rise[1]:.0f} us to the window), fall edge at {fall[0]:+.0f}.."
              f"{fall[1]:+.0f} us of the commanded end (margin {fall[0] + o.guard_us:.0f} us)")
    s.add("bench_pulse", PASS, detail, sn)
