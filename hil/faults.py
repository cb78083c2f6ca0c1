"""Fault switches of the bench.

Two kinds:

* **Link faults** (:class:`LinkFaults`, applied by :class:`FaultyLink` on the
  emulator's end of the link): every frame independently is dropped,
  corrupted (one bit flipped), truncated, duplicated, delayed (held back and
  delivered later, so out of order) or preceded by garbage bytes, each with
  its probability (seeded). Frames from the firmware are mangled too when
  ``both_ways`` is set (the incoming byte stream is split at the 0x00
  delimiters so each frame is mangled on its own).
* **Timed node and world faults** (:class:`TimedFault`, collected with the
  link faults in :class:`BenchFaults`): switched on (and optionally off) at
  true times: clock drift and clock steps of a node, magnetometer
  saturation (a magnet on the sensor board), coil open circuit, coil short
  (over-current trip), supply sag (battery), metal brought near the sensor,
  a node that disappears and comes back (reboots).

One text form for the command line (``coiltrack bench --faults``), comma
separated, keys may repeat::

    drop=P corrupt=P truncate=P duplicate=P garbage=P delay=P    per-frame probabilities
    delay_ms=MS                    how long a delayed frame is held (default 20 ms)
    jitter_ms=MS                   every frame, both ways, arrives late by a random latency
                                   (exponential, mean MS; order kept): a loaded host or a USB adapter
    both_ways=1                    also mangle frames from the firmware
    drift=[NODE:]PPM               oscillator drift (default: sensor +PPM and driver -PPM)
    clock_step=[NODE:]STEP@T       the node's time-stamp counter jumps by STEP (e.g. 5ms, -3ms)
    sat=WHEN                       magnet on the sensor board: the magnetometer saturates
    open_circuit=COIL@WHEN         coil winding open
    short=COIL@WHEN                coil shorted: the driver trips on over-current
    sag=FACTOR@WHEN                supply voltage drops to FACTOR x nominal (battery)
    overheat=COIL@WHEN             the winding is hot (150 C) while it lasts: over-temperature refusals
    metal=WHEN                     steel part carried next to the sensor (metal_d=M, metal_r=M)
    node_off=NODE@WHEN             node silent, then reboots (its clock restarts, it must re-sync)

``NODE`` is ``sensor`` (default) or ``driver``; ``WHEN`` is ``T`` (from T on)
or ``T1-T2`` or ``T+D``; times take a unit ``s``, ``ms`` or ``us`` (bare
numbers are seconds). Example:
``--faults drop=0.01,clock_step=5ms@20s,open_circuit=1@20s-30s,metal=30s,node_off=sensor@40s-43s``.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields

import numpy as np

def _number(what: str, text: str, lo: float, hi: float) -> float:
    """``text`` as a finite number in ``[lo, hi]``; ValueError naming ``what`` and the range otherwise."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{what} must be a number in [{lo:g}, {hi:g}], got '{text.strip()}'")
    return v


def _coil(text: str) -> int:
    """A coil index (checked against the source by :meth:`BenchFaults.check_coils`)."""
    if not text.strip().isdigit():
        raise ValueError(f"the coil must be an index 0, 1, 2, ..., got '{text.strip()}'")
    return int(text)


_LINK_PROBS = ("drop", "corrupt", "truncate", "duplicate", "garbage", "delay")


@dataclass
class LinkFaults:
    drop: float = 0.0        # probability a frame is lost
    corrupt: float = 0.0     # probability one bit of a frame flips
    truncate: float = 0.0    # probability a frame is cut short (its delimiter kept)
    duplicate: float = 0.0   # probability a frame is sent twice
    garbage: float = 0.0     # probability random bytes are inserted before a frame
    delay: float = 0.0       # probability a frame is held back by delay_us (arrives out of order)
    delay_us: int = 20_000
    both_ways: bool = False
    jitter_us: int = 0       # mean of the exponential latency every frame gets (order kept)

    def active(self) -> bool:
        return bool(self.jitter_us) or any(getattr(self, k) for k in _LINK_PROBS)

    def set(self, key: str, val: str) -> None:
        if key == "both_ways":
            self.both_ways = val.strip().lower() in ("1", "true", "yes", "")
            return
        if key == "delay_ms":
            self.delay_us = int(round(_number("link fault 'delay_ms'", val, 0.0, 10_000.0) * 1000))
            return
        if key == "jitter_ms":
            self.jitter_us = int(round(_number("link fault 'jitter_ms'", val, 0.0, 1_000.0) * 1000))
            return
        setattr(self, key, _number(f"link fault '{key}': the probability", val, 0.0, 1.0))

    @classmethod
    def parse(cls, spec: str) -> "LinkFaults":
        """``"corrupt=0.01,drop=0.005"`` -> LinkFaults (link keys only)."""
        lf = cls()
        if not spec:
            return lf
        names = set(_LINK_PROBS) | {"both_ways", "delay_ms", "jitter_ms"}
        for part in spec.split(","):
            key, _, val = part.partition("=")
            key = key.strip()
            if key not in names:
                raise ValueError(f"unknown link fault '{key}' (known: {', '.join(sorted(names))})")
            lf.set(key, val)
        return lf


class FaultyLink:
    """Wraps the emulator's end of a link and mangles frames (see the module docstring).

    ``service(now_us)`` (called by the emulator every step) releases delayed
    frames whose time has come; without it delayed frames go out on the next
    write. A byte link like the one it wraps: ``read``, ``write``, ``close`` (the link
    contract ``coiltrack.firmware.port.Port``, structurally: ``hil`` never imports the firmware).
    """

    def __init__(self, link, faults: LinkFaults, seed: int = 0):
        self.link = link
        self.faults = faults
        self.rng = np.random.default_rng(seed)
        self.counts = {"dropped": 0, "corrupted": 0, "truncated": 0, "duplicated": 0, "garbage": 0,
                       "delayed": 0}
        self.now_us = 0
        self._held_out: list[tuple[int, bytes]] = []
        self._held_in: list[tuple[int, bytes]] = []
        self._rx_partial = bytearray()
        self._jit_out = 0                  # release time of the last jittered frame, each way
        self._jit_in = 0
        self._jrng = np.random.default_rng(seed + 104729)

    def _mangle(self, data: bytes, held: list) -> bytes:
        f, rng = self.faults, self.rng
        out = b""
        if f.garbage and rng.random() < f.garbage:
            out += bytes(rng.integers(1, 256, int(rng.integers(1, 40)), dtype=np.uint8))
            self.counts["garbage"] += 1
        if f.drop and rng.random() < f.drop:
            self.counts["dropped"] += 1
            return out
        if f.corrupt and rng.random() < f.corrupt and len(data) > 1:
            b = bytearray(data)
            i = int(rng.integers(0, len(b) - 1))   # keep the final delimiter
            b[i] ^= 1 << int(rng.integers(0, 8))
            data = bytes(b)
            self.counts["corrupted"] += 1
        if f.truncate and rng.random() < f.truncate and len(data) > 2:
            cut = int(rng.integers(1, len(data) - 1))
            data = data[:cut] + data[-1:]
            self.counts["truncated"] += 1
        if f.delay and rng.random() < f.delay:
            held.append((self.now_us + f.delay_us, data))
            self.counts["delayed"] += 1
            return out
        out += data
        if f.duplicate and rng.random() < f.duplicate:
            out += data
            self.counts["duplicated"] += 1
        return out

    @staticmethod
    def _due(held: list, now_us: int) -> bytes:
        out = b""
        keep = []
        for t, d in held:
            if t <= now_us:
                out += d
            else:
                keep.append((t, d))
        held[:] = keep
        return out

    def _jitter(self, data: bytes, held: list, last: int) -> int:
        """Hold ``data`` for an exponential latency, after every frame held before it (order kept);
        returns its release time."""
        t = max(last, self.now_us + int(self._jrng.exponential(self.faults.jitter_us)))
        held.append((t, data))
        return t

    def service(self, now_us: int) -> None:
        self.now_us = int(now_us)
        due = self._due(self._held_out, self.now_us)
        if due:
            self.link.write(due)

    def close(self) -> None:
        """Close the wrapped link (frames still held back are dropped)."""
        close = getattr(self.link, "close", None)
        if close is not None:
            close()

    def write(self, data: bytes) -> None:
        out = self._mangle(data, self._held_out)
        if out and self.faults.jitter_us:
            self._jit_out = self._jitter(out, self._held_out, self._jit_out)
        elif out:
            self.link.write(out)

    def read(self) -> bytes:
        data = self.link.read()
        f = self.faults
        if not (f.both_ways or f.jitter_us):
            return data
        out = bytearray(self._due(self._held_in, self.now_us))
        if data:
            buf = self._rx_partial + data
            start = 0
            while True:
                z = buf.find(b"\x00", start)
                if z < 0:
                    break
                frame = bytes(buf[start:z + 1])
                if f.both_ways:
                    frame = self._mangle(frame, self._held_in)
                if frame and f.jitter_us:
                    self._jit_in = self._jitter(frame, self._held_in, self._jit_in)
                else:
                    out += frame
                start = z + 1
            self._rx_partial = bytearray(buf[start:])
            if f.jitter_us:
                out += self._due(self._held_in, self.now_us)
        return bytes(out)

    def flush(self) -> None:
        fl = getattr(self.link, "flush", None)
        if fl is not None:
            fl()


# ---------------------------------------------------------------------------
# Timed node and world faults
# ---------------------------------------------------------------------------

_UNITS = {"s": 1_000_000, "ms": 1_000, "us": 1}
_TIMED = ("clock_step", "sat", "open_circuit", "short", "sag", "overheat", "metal", "node_off")
_NODES = ("sensor", "driver")
_COIL_FAULTS = ("open_circuit", "short", "overheat")


def parse_time_us(text: str) -> int:
    """``"20s"``, ``"1500ms"``, ``"250us"``, ``"-5ms"`` or a bare number of seconds -> microseconds."""
    m = re.fullmatch(r"\s*([+-]?[0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(s|ms|us)?\s*", text)
    if not m:
        raise ValueError(f"'{text}' is not a time (use e.g. 20s, 1500ms, 250us)")
    return int(round(float(m.group(1)) * _UNITS[m.group(2) or "s"]))


def parse_when(text: str) -> tuple[int, int | None]:
    """``"20s"`` -> (20e6, None); ``"20s-25s"`` / ``"20s+5s"`` -> (20e6, 25e6)."""
    m = re.fullmatch(r"\s*([^+-]+?)\s*([+-])\s*(.+)", text)
    if m:
        t0 = parse_time_us(m.group(1))
        t1 = parse_time_us(m.group(3))
        t1 = t0 + t1 if m.group(2) == "+" else t1
        if t1 <= t0:
            raise ValueError(f"'{text}': the end must come after the start")
        return t0, t1
    return parse_time_us(text), None


@dataclass
class TimedFault:
    """One switch: ``kind`` on ``target`` (node name or coil index) with ``value`` on ``[t_on, t_off)``."""
    kind: str
    t_on_us: int
    t_off_us: int | None = None
    target: str | int | None = None
    value: float | None = None

    def active(self, t_us: int) -> bool:
        return t_us >= self.t_on_us and (self.t_off_us is None or t_us < self.t_off_us)

    def describe(self) -> str:
        when = f"{self.t_on_us / 1e6:g}s" + ("" if self.t_off_us is None else f"-{self.t_off_us / 1e6:g}s")
        tgt = "" if self.target is None else f"{self.target}:"
        val = "" if self.value is None else f"{self.value:g}"
        return f"{self.kind}={tgt}{val}@{when}"


@dataclass
class BenchFaults:
    """Every fault switch of one run: link faults plus timed node/world faults."""
    link: LinkFaults = field(default_factory=LinkFaults)
    timed: list[TimedFault] = field(default_factory=list)
    drift_ppm: dict = field(default_factory=dict)     # node name -> ppm (overrides the scenario's)
    metal_distance_m: float = 0.06
    metal_radius_m: float = 0.02

    def active(self) -> bool:
        return self.link.active() or bool(self.timed) or bool(self.drift_ppm)

    def of(self, kind: str, target=None) -> list[TimedFault]:
        return [f for f in self.timed if f.kind == kind and (target is None or f.target == target)]

    def at(self, kind: str, t_us: int, target=None) -> TimedFault | None:
        """The fault of ``kind`` (on ``target``) active at true time ``t_us``, if any."""
        for f in self.timed:
            if f.kind == kind and (target is None or f.target == target) and f.active(t_us):
                return f
        return None

    def describe(self) -> list[str]:
        out = [f"{k}={getattr(self.link, k):g}" for k in _LINK_PROBS if getattr(self.link, k)]
        if self.link.delay:
            out.append(f"delay_ms={self.link.delay_us / 1000:g}")
        if self.link.both_ways:
            out.append("both_ways=1")
        out += [f"drift={n}:{v:g}" for n, v in self.drift_ppm.items()]
        out += [f.describe() for f in self.timed]
        return out

    def check_coils(self, n_coils: int) -> "BenchFaults":
        """Self, or ValueError for a fault on a coil the source does not have."""
        for f in self.timed:
            if f.kind in _COIL_FAULTS and not 0 <= f.target < n_coils:
                raise ValueError(f"fault '{f.kind}' on coil {f.target}: the source has coils "
                                 f"0..{n_coils - 1}")
        return self

    @classmethod
    def parse(cls, spec: str) -> "BenchFaults":
        bf = cls()
        if not spec:
            return bf
        link_keys = set(_LINK_PROBS) | {"both_ways", "delay_ms", "jitter_ms"}
        known = sorted(link_keys | set(_TIMED) | {"drift", "metal_d", "metal_r"})
        for part in spec.split(","):
            if not part.strip():
                continue
            key, _, val = part.partition("=")
            key, val = key.strip(), val.strip()
            if key in link_keys:
                bf.link.set(key, val)
                continue
            if key not in known:
                raise ValueError(f"unknown fault '{key}' (known: {', '.join(known)})")
            try:
                bf._parse_one(key, val)
            except ValueError as exc:
                raise ValueError(f"fault '{key}={val}': {exc}") from None
        return bf

    def _parse_one(self, key: str, val: str) -> None:
        if key == "metal_d":
            self.metal_distance_m = _number("the distance (m)", val, 1e-3, 10.0)
            return
        if key == "metal_r":
            self.metal_radius_m = _number("the radius (m)", val, 1e-3, 1.0)
            return
        if key == "drift":
            node, _, ppm = val.rpartition(":")
            ppm = _number("the drift (ppm)", ppm, -1000.0, 1000.0)
            if node:
                self.drift_ppm[_node(node)] = ppm
            else:
                self.drift_ppm.update({"sensor": ppm, "driver": -ppm})
            return
        head, at, when = val.partition("@")
        if not at:
            head, when = "", val
        t0, t1 = parse_when(when)
        if key == "clock_step":
            node, _, step = head.rpartition(":")
            self.timed.append(TimedFault(key, t0, None, _node(node or "sensor"), parse_time_us(step)))
        elif key in ("sat", "metal"):
            if head:
                raise ValueError("takes only a time, e.g. 20s or 20s-30s")
            self.timed.append(TimedFault(key, t0, t1, "sensor"))
        elif key in ("open_circuit", "short"):
            self.timed.append(TimedFault(key, t0, t1, _coil(head)))
        elif key == "overheat":
            self.timed.append(TimedFault(key, t0, t1, _coil(head), 150.0))
        elif key == "sag":
            f = _number("the sag factor", head, 0.0, 1.0)
            if f == 0.0:
                raise ValueError("sag factor must be in (0, 1]")
            self.timed.append(TimedFault(key, t0, t1, "driver", f))
        elif key == "node_off":
            if t1 is None:
                raise ValueError("node_off needs an interval, e.g. sensor@20s-23s")
            self.timed.append(TimedFault(key, t0, t1, _node(head or "sensor")))


def _node(name: str) -> str:
    name = name.strip().lower()
    if name not in _NODES:
        raise ValueError(f"unknown node '{name}' (use {' or '.join(_NODES)})")
    return name
