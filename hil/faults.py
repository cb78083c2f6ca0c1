"""Link faults: dropped, corrupted, truncated and duplicated frames.

``FaultyLink`` wraps the emulator's end of a link. Every ``write`` from the
emulator is one frame; each frame independently suffers a fault with the
configured probability (seeded). Frames from the firmware pass untouched
unless ``both_ways`` is set.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass
class LinkFaults:
    drop: float = 0.0        # probability a frame is lost
    corrupt: float = 0.0     # probability one bit of a frame flips
    truncate: float = 0.0    # probability a frame is cut short (its delimiter kept)
    duplicate: float = 0.0   # probability a frame is sent twice
    garbage: float = 0.0     # probability random bytes are inserted before a frame
    both_ways: bool = False

    def active(self) -> bool:
        return any(getattr(self, f.name) for f in fields(self) if f.name != "both_ways")

    @classmethod
    def parse(cls, spec: str) -> "LinkFaults":
        """``"corrupt=0.01,drop=0.005"`` -> LinkFaults."""
        lf = cls()
        if not spec:
            return lf
        names = {f.name for f in fields(cls)}
        for part in spec.split(","):
            key, _, val = part.partition("=")
            key = key.strip()
            if key not in names:
                raise ValueError(f"unknown link fault '{key}' (known: {', '.join(sorted(names))})")
            if key == "both_ways":
                lf.both_ways = val.strip().lower() in ("1", "true", "yes", "")
                continue
            try:
                p = float(val)
            except ValueError:
                raise ValueError(f"link fault '{key}': '{val}' is not a number") from None
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"link fault '{key}': probability {p} outside [0, 1]")
            setattr(lf, key, p)
        return lf


class FaultyLink:
    def __init__(self, link, faults: LinkFaults, seed: int = 0):
        self.link = link
        self.faults = faults
        self.rng = np.random.default_rng(seed)
        self.counts = {"dropped": 0, "corrupted": 0, "truncated": 0, "duplicated": 0, "garbage": 0}

    def _mangle(self, data: bytes) -> bytes:
        f, rng = self.faults, self.rng
        out = b""
        if f.garbage and rng.random() < f.garbage:
            out += bytes(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8))
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
        out += data
        if f.duplicate and rng.random() < f.duplicate:
            out += data
            self.counts["duplicated"] += 1
        return out

    def write(self, data: bytes) -> None:
        self.link.write(self._mangle(data))

    def read(self) -> bytes:
        data = self.link.read()
        if data and self.faults.both_ways:
            return self._mangle(data)
        return data
