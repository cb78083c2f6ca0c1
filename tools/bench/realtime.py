"""Wall-clock loops: the firmware at a fixed tick and the emulator beside it,
as two processes joined by a pseudo-terminal (``coiltrack bench --transport
pty``), or each alone against a real board (``coiltrack firmware``,
``coiltrack emulator``).

Both loops take the clock and the sleep function as arguments, so the tests
drive them with a simulated clock (no wall-clock sleeps in tests).

In the two-process bench the firmware runs at SCHED_FIFO above the
emulator's loop, each on its own CPU kept from idling (:class:`KeepAwake`),
the emulator's physics computed ahead between steps; where the misses and
the latency come from is in ``docs/bench-realtime.md``.

Timing figures (all in microseconds):

* tick period jitter: ``|start_k - start_(k-1) - tick|`` over consecutive
  ticks (median, p99, max);
* lateness: ``start_k - scheduled_k``;
* execution time of ``fw.tick``;
* deadline misses: ticks that started a whole period late or ran longer than
  a period, plus every tick slot skipped because the loop fell behind.

In-process runs use the simulated clock, where the tick period is exact by
construction; there :func:`inproc_timing` measures the wall time of each
``fw.tick`` and replays it on an ideal real-time schedule (a tick starts at
its slot or when the previous one ends, whichever is later), giving the same
figures a dedicated core would show for the firmware alone.
"""
from __future__ import annotations

import gc
import json
import os
import select
import subprocess
import sys
import time

import numpy as np

from coiltrack.firmware.measure.pulse import NO_TIME_US
from coiltrack.hil.clock import WallClock

from .links import FdLink, make_raw_pty
from .timing import _stats, inproc_timing, no_ticks  # noqa: F401  (inproc_timing: for the callers of realtime)
from ..stopping import Stopped, held_signals, mark, start_child, stop_child
from .. import args as A
from ..outputs import report as report_mod


#: time the firmware process is given to start (imports, set-up, memory locked) before the shared
#: epoch: one that starts late finds the nodes unsynchronised and its first commands refused
#: (1.5 s was too short on a loaded 2-CPU machine: imports alone took 1.4 s there)
CHILD_START_NS = 3_000_000_000
#: SCHED_FIFO priorities of the two-process bench: the firmware above the emulator (on one CPU a
#: firmware tick preempts an emulator step), both below the kernel's threaded interrupts (50)
FIRMWARE_RT_PRIORITY = 30
EMULATOR_RT_PRIORITY = 20
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4
#: the firmware loop sleeps until this long before each tick's slot and polls the clock for the rest.
#: A SCHED_FIFO loop polling its CPU keeps the kernel's tty flush work (a kworker of ordinary
#: priority, which moves the bytes written to a pty or a serial port to the reader) off that CPU
#: until the tick has run: with 200 us, 84-87 % of the emulator's writes made in the last 200 us
#: before a tick were read a tick late (2-7 % of the others); the loop's sleeps end 22 us late at
#: the median, 35 us at p90, 64 us at p99 (traced, ``docs/bench-realtime.md``), so 50 us keeps
#: nearly every tick on its slot and leaves the CPU to the flush work for all but ~50 us
SPIN_US = 50


def _lock_memory() -> bool:
    """``mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)``: every page the process has touched stays
    resident from now on, so no tick waits on a page the kernel reclaimed (a memory-pressure or
    page-out daemon) and faults back in; ``MCL_ONFAULT`` (Linux 4.4) locks pages as they are
    touched instead of faulting in every mapped library at once (about 280 MB without it). Best
    effort: False when not permitted."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) == 0:
            return True
        return libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0
    except (OSError, AttributeError):
        return False


def _realtime_setup(cpu: int | None, priority: int = FIRMWARE_RT_PRIORITY, lock_memory: bool = True) -> dict:
    """Best effort: pin to one CPU, ask for SCHED_FIFO at ``priority``, lock the process's memory,
    freeze and disable the cyclic GC."""
    info = {}
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {cpu})
            info["cpu"] = cpu
        except OSError:
            pass
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        info["sched"] = "fifo"
        info["priority"] = priority
    except (AttributeError, OSError, PermissionError):
        info["sched"] = "other"
    gc.collect()
    gc.freeze()
    gc.disable()
    info["gc"] = "disabled"
    if lock_memory:
        info["mlock"] = _lock_memory()
    return info


_SPIN = ("import os, sys\n"
         "try:\n"
         "    os.sched_setaffinity(0, {int(sys.argv[1])})\n"
         "    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
         "except (AttributeError, OSError):\n"
         "    sys.exit(0)\n"          # never spin at an ordinary priority
         "while True:\n"
         "    pass\n")


class KeepAwake:
    """A SCHED_IDLE busy loop on each of ``cpus`` while the block runs (best effort), so those
    CPUs never go idle between ticks. On a virtual machine an idle CPU halts and the host
    deschedules it; the timer that ends a tick's sleep then waits for the host to run the CPU
    again: a firmware loop whose tick does nothing missed 951 deadlines in 20 s on an otherwise
    idle 2-CPU machine, 13 with this (``python -m coiltrack.tools.bench.realtime``). A SCHED_IDLE task
    runs only when nothing else wants the CPU, so it takes time from no one in this machine; it
    keeps the host's CPU busy for the run. The loops die with this process."""

    def __init__(self, cpus):
        self.cpus = sorted(set(int(c) for c in cpus))
        self.children: list = []

    def __enter__(self) -> "KeepAwake":
        if not hasattr(os, "SCHED_IDLE"):
            return self
        with held_signals():
            for c in self.cpus:
                self.children.append(start_child([sys.executable, "-S", "-c", _SPIN, str(c)],
                                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                                  stderr=subprocess.DEVNULL))
        return self

    def __exit__(self, *exc) -> None:
        for child in self.children:
            stop_child(child, grace_s=0.5)
        self.children = []


class EmulatorRealtime:
    """Around the wall-clock emulator loop of the two-process bench (best effort): SCHED_FIFO at
    ``EMULATOR_RT_PRIORITY`` (below the firmware's), so a due sample leaves and a ``POSE`` is
    stamped when it arrives rather than when the CPU's other work yields, and the cyclic GC
    frozen and off (a run of bounded length; no collection pause in a step). Restored on exit,
    so the report and any in-process comparison runs after it are ordinary work."""

    def __init__(self, priority: int = EMULATOR_RT_PRIORITY, threads=()):
        self.priority = priority
        self.threads = tuple(threads)       # native ids of helper threads that serve the link
        self.info: dict = {}

    def __enter__(self) -> "EmulatorRealtime":
        self._gc = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        self._saved = []
        for tid in (0, *self.threads):
            try:
                pol, par = os.sched_getscheduler(tid), os.sched_getparam(tid)
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(self.priority))
                self._saved.append((tid, pol, par))
            except (AttributeError, OSError, PermissionError):
                pass
        self.info = {"emulator_sched": "fifo" if self._saved else "other"}
        return self

    def __exit__(self, *exc) -> None:
        for tid, pol, par in self._saved:
            try:
                os.sched_setscheduler(tid, pol, par)
            except OSError:
                pass
        gc.unfreeze()
        if self._gc:
            gc.enable()


def grid_shift(slot_us: int, want_us: int, tick_us: int) -> int:
    """How far to move a grid of ticks ``tick_us`` apart, one of them at ``slot_us``, so that one
    lies at ``want_us``: the shorter way round (negative: earlier), at most half a tick."""
    d = (slot_us - want_us) % tick_us         # the grid's ticks lie at want_us + d + k * tick_us
    return -d if 2 * d <= tick_us else tick_us - d


class GridAlign:
    """The wall-clock loop's grid moved onto the burst's completing sample (``[timing] align_us``):
    after each tick it reads when the firmware expects the sample that completes the open burst
    (``Firmware.completing_sample_us``, a prediction one sample interval ahead) and moves the
    following slots, by at most ``slew_us`` a tick (:func:`grid_shift`: the shorter way), so
    that a tick starts ``align_us`` after it and reads it as soon as it is in: the wait for the
    next tick (up to a whole tick) leaves the pose latency. Each tick's period stays within
    ``tick_us`` +/- ``slew_us``; the firmware is not told (it runs on the times it is given)."""

    def __init__(self, due, align_us: int, slew_us: int, tick_us: int):
        self.due = due
        self.align_us = int(align_us)
        self.slew_us = int(slew_us)
        self.tick_us = int(tick_us)
        self.left_us = 0                      # what the grid still has to move
        self.seen = None                      # the expected sample last aligned to
        self.moved_ticks = 0                  # ticks whose period was moved
        self.moved_us = 0                     # sum of |moves|

    def step(self, next_tick: int) -> int:
        """The slot after ``next_tick`` (the next one on the grid) moved by this tick's part."""
        t = self.due()
        if t != NO_TIME_US and t != self.seen:
            self.seen = t
            self.left_us = grid_shift(next_tick, t + self.align_us, self.tick_us)
        if not self.left_us:
            return next_tick
        m = max(-self.slew_us, min(self.slew_us, self.left_us))
        self.left_us -= m
        self.moved_ticks += 1
        self.moved_us += abs(m)
        return next_tick + m

    def report(self) -> dict:
        return {"tick_align_us": self.align_us, "tick_align_moves": self.moved_ticks,
                "tick_align_moved_us": self.moved_us}


def firmware_loop(fw, clock, duration_us: int, tick_us: int, sleep=None, spin_us: int = SPIN_US,
                  max_records: int = 600_000, after_tick=None, trace=None, align_us: int = 0,
                  slew_us: int = 0) -> dict:
    """Run ``fw.tick`` every ``tick_us`` of ``clock`` until ``duration_us``.

    Sleeps until ``spin_us`` (:data:`SPIN_US`) before each slot, then polls the clock (the
    sleep's wake-up latency does not become jitter); with a simulated clock,
    which only moves when slept, pass ``spin_us=0``. Measures period jitter,
    lateness, execution time and deadline misses (a tick that starts a whole
    period late or runs longer than a period, and every slot skipped because
    the loop fell behind). Buffers are sized up front. Stopped early (a
    :class:`tools.stopping.Stopped` from a signal or from the port), the
    statistics of the ticks run so far go with the exception as ``partial``.
    ``after_tick()``, when given, runs after each tick, inside its measured
    execution time (a link's ``flush``: the tick's frames leave in one write).
    ``trace``: a :class:`tools.bench.timing.LoopTrace` recording each tick's gap, sleeps and
    stage times (None, the default: nothing recorded, nothing allocated). ``align_us`` > 0
    (``[timing] align_us``) with a firmware that hints when a burst completes
    (``completing_sample_us``): the grid is moved by at most ``slew_us`` a tick so that a tick
    starts ``align_us`` after that sample (:class:`GridAlign`).
    """
    if sleep is None:
        sleep = getattr(clock, "sleep", time.sleep)
    n_max = duration_us // tick_us + 2
    cap = int(min(n_max, max_records))      # statistics over the last ``max_records`` ticks
    starts = np.zeros(cap, dtype=np.int64)
    exec_us = np.zeros(cap, dtype=np.int64)
    late = np.zeros(cap, dtype=np.int64)
    n = 0
    misses = 0
    stopped = None
    due = getattr(fw, "completing_sample_us", None) if align_us > 0 and slew_us > 0 else None
    align = GridAlign(due, align_us, slew_us, tick_us) if due is not None else None
    try:
        next_tick = max(0, clock.now())
        next_tick += (-next_tick) % tick_us
        while True:
            now = clock.now()
            if now >= duration_us:
                break
            if now < next_tick:
                rem = next_tick - now
                if rem > spin_us:
                    sleep((rem - spin_us) * 1e-6)
                    if trace is not None:
                        trace.slept(rem - spin_us, clock.now() - now)
                continue
            t0 = now
            if trace is None:
                fw.tick(t0)
            else:
                fw.tick_timed(t0, trace.stages)
            if after_tick is not None:
                after_tick()
            t1 = clock.now()
            if trace is not None:
                trace.tick(t0, t1)
            i = n % cap
            starts[i] = t0
            exec_us[i] = t1 - t0
            late[i] = t0 - next_tick
            n += 1
            if t0 - next_tick >= tick_us or t1 - t0 >= tick_us:
                misses += 1
            next_tick += tick_us
            if align is not None:
                next_tick = align.step(next_tick)
            if next_tick <= t1 - tick_us:          # fell behind: skip missed slots, count them
                skipped = (t1 - next_tick) // tick_us
                misses += int(skipped)
                next_tick += skipped * tick_us
    except Stopped as exc:
        stopped = exc
    if n > cap:
        r = -(n % cap)
        starts, exec_us, late = np.roll(starts, r), np.roll(exec_us, r), np.roll(late, r)
    m = min(n, cap)
    out = _stats(starts[:m], exec_us[:m], late[:m], tick_us, misses)
    out["ticks"] = n
    out["timing_source"] = "wall clock: tick start times and execution times"
    if align is not None:
        out.update(align.report())
    if stopped is not None:
        stopped.partial = out
        raise stopped
    return out


def _fd_of(link):
    while link is not None:
        fd = getattr(link, "fd", None)
        if fd is not None:
            return fd
        link = getattr(link, "link", None)
    return None


#: how far ahead of true time the wall-clock emulator keeps its nodes' physics (us); under the
#: 2 s that ``hil.world.World.precompute`` keeps behind its newest instants, so nothing computed
#: ahead is dropped before it is used
AHEAD_US = 1_500_000
#: sample instants computed in one piece between steps (a piece costs the trajectory's fixed
#: evaluation, ~0.5-1.5 ms, plus ~50 us an instant)
PREFETCH_PIECE = 8
#: a piece is computed only when the next sample is due at least this far away (us)
PREFETCH_GUARD_US = 3_000
#: ... and only this long after the last step that wrote to the link (us): the firmware's answer (a
#: ``POSE`` to the sample that completed a burst) comes within this, and a piece computed meanwhile
#: at the loop's SCHED_FIFO priority delays its stamp by the piece's cost and, on this CPU, keeps
#: the tty layer's flush work (a kworker of ordinary priority, which moves the written bytes to
#: the reader) from running: the firmware then read 22 % of the samples one to three ticks late
PREFETCH_AFTER_SEND_US = 3_000
#: the next sample of each sensor is computed and encoded ahead (``Emulator.prepare``) once it is
#: due within this (us), outside the PREFETCH_AFTER_SEND_US after a write like a piece, so that
#: the step at its instant only writes its bytes (a sample step that computes its physics, noise
#: and frame took 0.4 ms of the pose latency); computed again when a pulse committed or a flip
#: commanded since changes it. The coil driver commits a pulse 2 ms before its start
#: (``CoilDriverNode.commit_horizon_us``): a sample prepared earlier than that is computed
#: twice when a pulse starts before it
PREPARE_AHEAD_US = 6_000


class EmulatorTiming:
    """What the wall-clock emulator loop measured (us): each step's duration, and how late
    each step that took a sample started after that sample's instant (the sample leaves the
    emulator that late; the pose latency counts it). ``cap`` steps at most (the last ones)."""

    def __init__(self, cap: int = 1 << 20):
        self.step_us = np.zeros(cap, dtype=np.int64)
        self.late_us = np.zeros(cap, dtype=np.int64)
        self.steps = 0
        self.samples = 0
        self.prefetched = 0
        self.pieces = 0
        self.prepares = 0                   # Emulator.prepare calls that computed or encoded a sample
        self.worst_late_us = -1
        self.sched = None                   # the emulator loop's scheduling policy (EmulatorRealtime)
        self.worst_late_at_us = None        # true time of the step that sent a sample latest
        self.stalls = None                  # with a trace: (at_us, what, us, steal_cs) of each long gap
        self.probe = None

    def trace(self) -> None:
        """Record each gap over 5 ms (a wait, a step, a sample's lateness) with the CPU's steal."""
        from .timing import StealProbe

        self.stalls, self.probe = [], StealProbe()
        self._marked = 0
        self.io = []                        # (t_us, bytes_rx, bytes_tx) after each step that moved bytes

    def io_mark(self, t_us: int, link, t_flushed: int) -> None:
        if self.stalls is None:
            return
        rx, tx = getattr(link, "bytes_rx", 0), getattr(link, "bytes_tx", 0)
        if not self.io or self.io[-1][2] != rx or self.io[-1][3] != tx:
            self.io.append((t_us, t_flushed, rx, tx))

    def gap(self, now: int, what: str, us: int) -> None:
        if self.stalls is None:
            return
        if us > 5000:
            self.stalls.append((now, what, us, self.probe.delta()))
        if now - self._marked > 200_000:
            self.probe.mark()
            self._marked = now

    def add_step(self, dt_us: int) -> None:
        self.step_us[self.steps % self.step_us.size] = dt_us
        self.steps += 1

    def add_late(self, late_us: int, at_us: int | None = None) -> None:
        self.late_us[self.samples % self.late_us.size] = late_us
        self.samples += 1
        if late_us > self.worst_late_us:
            self.worst_late_us, self.worst_late_at_us = late_us, at_us

    def report(self) -> dict:
        st = self.step_us[:min(self.steps, self.step_us.size)]
        la = self.late_us[:min(self.samples, self.late_us.size)]
        pct = lambda a, q: float(np.percentile(a, q)) if a.size else None  # noqa: E731
        return {"emulator_step_us_p99": pct(st, 99), "emulator_step_us_max": pct(st, 100),
                "emulator_sample_late_us_p50": pct(la, 50), "emulator_sample_late_us_p99": pct(la, 99),
                "emulator_sample_late_us_max": pct(la, 100),
                "emulator_sample_late_max_at_s": (round(self.worst_late_at_us * 1e-6, 3)
                                                  if self.worst_late_at_us is not None else None),
                "emulator_prefetched_instants": self.prefetched, "emulator_prefetch_pieces": self.pieces,
                "emulator_prepares": self.prepares,
                "emulator_sched": self.sched, **({"emulator_stalls": self.stalls, "emulator_io": self.io} if self.stalls is not None else {})}


def emulator_loop(emulator, link, clock, duration_us: int, progress=None, step_us: int = 250, wait=None,
                  timing: EmulatorTiming | None = None, ahead_us: int = AHEAD_US) -> None:
    """Step the emulator on ``clock`` until ``duration_us``.

    Waits until the next sample is due (``emulator.next_due_us()``, when the
    emulator tells), at most ``step_us``, and wakes at once when bytes arrive
    on a file-descriptor link (``select``), so a node stamps a ``TIME_SYNC``
    close to its arrival and the recorder a ``POSE``. Frames written in a step
    go out together at its end (``link.flush``). The nodes' physics is
    computed ahead of the sampling path (``emulator.prefetch``): the first
    ``ahead_us`` before the run starts (``clock.now() < 0``), then a piece of
    ``PREFETCH_PIECE`` instants between steps, while the next sample is more
    than ``PREFETCH_GUARD_US`` away and the last step that wrote to the link
    (``link.bytes_tx``, where it counts) is ``PREFETCH_AFTER_SEND_US`` past,
    keeping ``ahead_us`` in hand (0: none); before a piece, under the same
    rule, the next sample of each sensor due within ``PREPARE_AHEAD_US``
    (``emulator.prepare``), so the step at its instant only writes its bytes.
    ``wait(timeout_s)`` replaces the wait (tests pass a simulated one);
    ``timing`` (:class:`EmulatorTiming`) collects step durations and sample
    lateness.
    """
    fd = _fd_of(link)
    if wait is None:
        if fd is not None:
            def wait(timeout_s, _fd=fd):
                select.select([_fd], [], [], timeout_s)
        else:
            wait = getattr(clock, "sleep", time.sleep)
    flush = getattr(link, "flush", None)
    sent = -1 if hasattr(link, "bytes_tx") else None    # bytes written so far (None: not counted)
    quiet_from = 0                                      # no piece before this time (PREFETCH_AFTER_SEND_US)
    next_due = getattr(emulator, "next_due_us", None)
    prefetch = getattr(emulator, "prefetch", None) if ahead_us > 0 else None
    prepare = getattr(emulator, "prepare", None) if ahead_us > 0 else None
    if prefetch is not None:
        # before the start: the first ahead_us of every node, in pieces (the clock runs meanwhile)
        n = 1
        while n and clock.now() < 0:
            n = prefetch(ahead_us, 256)
            if timing is not None:
                timing.prefetched += n
    while True:
        now = clock.now()
        if now > duration_us:
            break
        timeout_us = step_us
        if now >= 0:
            due = next_due() if next_due is not None else None
            emulator.step(now)
            if flush is not None:
                flush()
            if timing is not None:
                timing.io_mark(now, link, clock.now())
            if progress is not None:
                progress.update(now * 1e-6, len(emulator.recorder.poses))
            t1 = clock.now()
            if timing is not None:
                timing.add_step(t1 - now)
                if due is not None and due <= now:
                    timing.add_late(now - due, now)
                    timing.gap(now, "late", now - due)
                timing.gap(t1, "step", t1 - now)
            if sent is not None and link.bytes_tx != sent:
                sent, quiet_from = link.bytes_tx, t1 + PREFETCH_AFTER_SEND_US
            if t1 - now > step_us:
                continue        # a long step: read the link again at once
            nxt = next_due() if next_due is not None else None
            if t1 >= quiet_from and _work_ahead(prepare, prefetch, nxt, clock, t1, ahead_us, timing):
                continue        # it took time: read the link again at once
            if nxt is not None:
                timeout_us = min(step_us, max(0, nxt - clock.now()))
        if timing is not None and timing.stalls is not None:
            tw = clock.now()
            wait(timeout_us * 1e-6)
            timing.gap(clock.now(), "wait", clock.now() - tw - timeout_us)
        else:
            wait(timeout_us * 1e-6)


def _work_ahead(prepare, prefetch, nxt, clock, t1: int, ahead_us: int, timing) -> bool:
    """:func:`emulator_loop`'s work between steps, outside the quiet time after a write: the
    samples due within ``PREPARE_AHEAD_US`` computed and encoded (``prepare``), else a piece of
    physics (``prefetch``) while the next sample ``nxt`` is more than ``PREFETCH_GUARD_US`` away.
    True when it did some (the loop then reads the link again at once)."""
    if prepare is not None and prepare(t1 + PREPARE_AHEAD_US):
        if timing is not None:
            timing.prepares += 1
            timing.gap(clock.now(), "prepare", clock.now() - t1)
        return True
    if prefetch is None or (nxt is not None and nxt - t1 <= PREFETCH_GUARD_US):
        return False
    n = prefetch(t1 + ahead_us, PREFETCH_PIECE, PREFETCH_PIECE)
    if n and timing is not None:
        timing.prefetched += n
        timing.pieces += 1
        timing.gap(clock.now(), "piece", clock.now() - t1)
    return bool(n)


def _two_process_link(transport: str):
    """The link between the two processes: (the firmware's link arguments, the emulator's
    end, a function that closes everything, native ids of threads that serve the link)."""
    if transport == "slcan":
        # a CAN bus between the two processes: an slcan adapter on each side of a bridge of
        # pseudo-terminals (protocol.slcan); same messages, CAN frames
        from coiltrack.protocol.can import CanLink, open_bus
        from coiltrack.protocol.schema import NODE_COIL_DRIVER
        from coiltrack.protocol.slcan import SlcanBridge

        bridge = SlcanBridge(2).start()
        # slcan-tty (protocol.interfaces.slcan): a read takes every line the pty holds in one system
        # call, a tick's (a step's) frames leave in one write at its flush
        link = CanLink(open_bus("slcan-tty", bridge.paths[0]), NODE_COIL_DRIVER)
        thread = getattr(bridge, "_thread", None)
        # the bridge's relay thread moves every frame both ways: it runs at the emulator's priority
        threads = (thread.native_id,) if getattr(thread, "native_id", None) else ()

        def close():
            link.close()
            bridge.stop()
        return ["--transport", "can", "--interface", "slcan-tty", "--channel", bridge.paths[1]], link, close, threads
    master, slave, slave_name = make_raw_pty()

    def close_pty():
        os.close(master)
        os.close(slave)
    # the emulator's frames of one step leave in one write (emulator_loop flushes after each step)
    return ["--port", slave_name], FdLink(master, coalesce=True), close_pty, ()


def _pin_cpus(cmd: list[str]) -> list[str]:
    """With two or more CPUs: the firmware on the last one (``--cpu``), this process on the
    others (:func:`_start_pinned` sets both)."""
    ncpu = os.cpu_count() or 1
    if ncpu < 2:
        return cmd
    return cmd + ["--cpu", str(ncpu - 1)]


def _start_pinned(cmd: list[str], **kw):
    """Start the child of ``cmd`` on the CPU its ``--cpu`` names, from its first instruction (its
    imports and set-up do not queue behind this process's work), then move this process to
    the other CPUs. Best effort where affinity cannot be set."""
    cpu = int(cmd[cmd.index("--cpu") + 1]) if "--cpu" in cmd else None
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        return start_child(cmd, **kw)
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError:
        return start_child(cmd, **kw)
    try:
        return start_child(cmd, **kw)
    finally:
        try:
            os.sched_setaffinity(0, set(range(os.cpu_count() or 1)) - {cpu})
        except OSError:
            pass


def _read_stats(stream) -> dict:
    """The firmware's statistics (``coiltrack firmware`` prints them as JSON at its end)."""
    try:
        with stream:
            return json.loads(stream.read())
    except (OSError, ValueError):
        return {"status": {}, "timing": {}}


def run_pty(scenario, seed: int, duration_s: float, faults=None, progress: bool = False,
            transport: str = "pty", cfg=None, config_path=None, outputs=None) -> dict:
    """Firmware in a child process (``coiltrack firmware``) on the slave side of
    a raw pseudo-terminal; emulator here on the master side; both on
    CLOCK_MONOTONIC from a shared epoch (the nodes still keep their own
    drifting clocks and synchronise to the firmware's broadcasts). On a
    machine with two or more CPUs the firmware is pinned to the last one and
    the emulator to the first. ``transport="slcan"`` puts the two on a CAN
    bus instead: python-can's slcan interface on each side of a bridge of
    pseudo-terminals. ``cfg``: the firmware configuration (default the
    scenario's), read by the child from ``config_path`` over the scenario's.

    The child dies with this process, and writes no file (its statistics come
    back on its standard output). Stopped early (SIGINT, SIGTERM), the child
    is stopped within a second and the report of what was done, marked
    ``interrupted``, goes with the exception as ``exc.partial``. ``outputs``
    (:mod:`coiltrack.tools.outputs`) taps the emulator's end of the link."""
    # here, not at the top: the firmware's process imports this module and needs no world
    from .runner import BenchSetup, Progress

    cfg = cfg or scenario.firmware_config()
    link_args, link, close, threads = _two_process_link(transport)
    epoch_ns = time.monotonic_ns() + CHILD_START_NS     # give the child time to start
    if outputs is not None:     # tools.outputs: the emulator's end of the link is tapped
        link = outputs.wrap(link, side="emulator", clock_us=WallClock(epoch_ns).now)
    try:
        bench = BenchSetup(scenario, seed, duration_s, link, faults, cfg=cfg)
        clock = WallClock(epoch_ns)
        # the child's statistics come back on its standard output (a few kB, written at its end)
        cmd = [sys.executable, "-m", "coiltrack.tools.cli", "firmware", *link_args, "--scenario", scenario.name,
               "--epoch-ns", str(epoch_ns), "--duration", str(duration_s + 0.5), "--realtime",
               *(["--config", str(config_path)] if config_path else []),
               *(["--calibration", cfg.calibration.calibration_file] if cfg.calibration.calibration_file else []),
               "--core", cfg.core.impl]
        env = None
        if cfg.signing.signing_key:     # the key reaches the child in its environment, not on its command line
            from ..args import KEY_ENV

            env = {**os.environ, KEY_ENV: cfg.signing.signing_key}
            cmd += ["--key", "@env"]
        emu_timing = EmulatorTiming()
        if os.environ.get("COILTRACK_LOOP_TRACE"):
            emu_timing.trace()
        stopped, code, fw_stats = _beside_child(_pin_cpus(cmd), bench, clock, duration_s,
                                                Progress(progress, duration_s, f"{scenario.name} ({transport})"),
                                                env, emu_timing, threads)
    finally:
        close()
    done_s = duration_s if stopped is None else elapsed_s(clock, duration_s)
    rep = report_mod.build(bench, fw_stats.get("status", {}), done_s, transport=transport, cfg=cfg)
    rep.update({k: v for k, v in fw_stats.get("timing", {}).items()})
    rep.update(emu_timing.report())
    # samples sent as the bytes prepared ahead, and those whose preparation no longer held at the instant
    rep["emulator_samples_prepared"] = getattr(bench.emulator, "ready_sent", 0)
    rep["emulator_samples_redone"] = sum(getattr(s, "prepared_redone", 0) for s in bench.sensors)
    rep["firmware_exit_code"] = code
    if emu_timing.stalls is not None:    # a traced run: each pose's completing sample and arrival
        from coiltrack.hil.bench import pose_latency_times

        rep["pose_latency_times"] = pose_latency_times(bench, cfg.pulse.fall_us, cfg.pulse.baseline_us)
    if outputs is not None:
        outputs.finish(bench, rep)
    if stopped is not None:
        raise mark(rep, stopped)
    return rep


def elapsed_s(clock, duration_s: float) -> float:
    """Seconds of a wall-clock run done by now (at least 1 ms, at most ``duration_s``)."""
    return min(duration_s, max(round(clock.now() * 1e-6, 3), 0.001))


#: seconds the firmware process has after its SIGTERM to end by itself (its statistics written)
FIRMWARE_GRACE_S = 5.0


def _beside_child(cmd: list[str], bench, clock, duration_s: float, prog, env=None, timing=None, threads=(),
                  keep_awake: bool = True):
    """Start the firmware process and run the emulator beside it (until 0.3 s after
    ``duration_s``, so the last frames arrive), the emulator's loop at SCHED_FIFO below the
    firmware (:class:`EmulatorRealtime`; ``threads``: helper threads of the link raised with
    it). Returns the :class:`Stopped` that ended the run early (or None), the child's exit
    status and its statistics (its standard output). ``timing``: an :class:`EmulatorTiming`;
    ``keep_awake``: this process's CPUs kept from idling meanwhile (:class:`KeepAwake`)."""
    child, stopped, wait_s = None, None, 0.0      # stopped or failed: the child goes at once
    try:
        with held_signals():
            child = _start_pinned(cmd, stdout=subprocess.PIPE, env=env)
        emu_cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
        with KeepAwake(emu_cpus if keep_awake else ()), EmulatorRealtime(threads=threads) as ert:
            if timing is not None:
                timing.sched = ert.info.get("emulator_sched")
            emulator_loop(bench.emulator, bench.link, clock, int(duration_s * 1e6) + 300_000, prog, timing=timing)
        wait_s = 30.0
    except Stopped as exc:
        stopped = exc
    finally:
        prog.done()
        # a stopped run gives the firmware FIRMWARE_GRACE_S after its SIGTERM to write its
        # statistics (a loaded machine can take seconds) before it is killed
        code = stop_child(child, wait_s=wait_s, grace_s=FIRMWARE_GRACE_S) if child is not None else None
    return stopped, code, _read_stats(child.stdout) if child is not None else {"status": {}, "timing": {}}


class _NullFirmware:
    """A firmware whose tick does nothing (the platform's floor)."""

    def tick(self, now_us: int) -> None:
        pass

    def tick_timed(self, now_us: int, out_ns) -> None:
        pass


def floor_main(argv=None) -> int:
    """``python -m coiltrack.tools.bench.realtime --cpu 1 --seconds 60``: the firmware loop with a tick
    that does nothing, at the firmware's CPU, priority and set-up; prints its timing (JSON). Its
    deadline misses are the ones the machine alone causes, the floor of the two-process bench's."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.bench.realtime", description=floor_main.__doc__)
    p.add_argument("--cpu", type=A.cpu, default=(os.cpu_count() or 1) - 1, help="CPU (default the last)")
    p.add_argument("--seconds", type=A.real(0.001, 3600.0), default=60.0, help="how long (default 60)")
    p.add_argument("--rt-priority", type=A.integer(1, 99), default=FIRMWARE_RT_PRIORITY, metavar="P")
    p.add_argument("--no-keep-awake", action="store_true", help="let the CPU idle between ticks (see KeepAwake)")
    p.add_argument("--trace", metavar="FILE", help="write the loop's per-tick trace (tools.bench.timing.LoopTrace, .npz)")
    a = p.parse_args(argv)
    from .timing import LoopTrace

    trace = LoopTrace(path=a.trace, cap=int(a.seconds * 1000) + 16) if a.trace else None
    with KeepAwake(() if a.no_keep_awake else (a.cpu,)):
        rt = _realtime_setup(a.cpu, a.rt_priority)
        out = firmware_loop(_NullFirmware(), WallClock(), int(a.seconds * 1e6), 1000, trace=trace)
    if trace is not None:
        trace.save()
    out.update({"rt_" + k: v for k, v in rt.items()})
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(floor_main())
