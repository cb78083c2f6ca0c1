"""An slcan "adapter emulator": a CAN bus between processes over
pseudo-terminals, for machines without a (v)can kernel module.

python-can's ``slcan`` interface speaks the Lawicel ASCII protocol to a
serial device: it writes commands (``C``, ``S6``, ``O``, ...) and frames
(``t1238DEADBEEF...``, ``d``/``b`` for CAN FD), each ended by ``\\r``, and
reads frames back as the same lines. :class:`SlcanBridge` creates one raw
pseudo-terminal per bus end and relays, in a thread, every frame line written
on one end to every other *open* end, as a bus would; commands are answered
with ``\\r`` (``V``/``N``/``F`` with a version, serial number and status),
malformed lines with ``\\a``. It keeps the slave side of each pty open so an
end can be closed and reopened. Transmit acknowledgements (``z``) are not
sent: python-can does not need them.

In one process::

    from coiltrack.protocol.slcan import SlcanBridge
    from coiltrack.protocol.can import open_bus, CanLink
    with SlcanBridge(2) as bridge:
        a = open_bus("slcan", bridge.paths[0], 500_000)
        b = open_bus("slcan", bridge.paths[1], 500_000)   # or in another process
        ...
        a.shutdown(); b.shutdown()

As its own process: ``python -m coiltrack.protocol.slcan [--ends N] [--exit-on-eof]``
prints one pty path per line, then relays until SIGTERM/SIGINT (or, with
``--exit-on-eof``, until its stdin closes).
"""
from __future__ import annotations

import os
import re
import selectors
import threading

#: slcan bitrate commands ``S0``..``S9`` -> bit/s (as python-can's table)
SLCAN_BITRATES = {"S0": 10_000, "S1": 20_000, "S2": 50_000, "S3": 100_000, "S4": 125_000,
                  "S5": 250_000, "S6": 500_000, "S7": 750_000, "S8": 1_000_000, "S9": 83_300}
_FD_DLC = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_HEX = re.compile(rb"^[0-9A-Fa-f]*$")
MAX_LINE = 160


def frame_line_ok(line: bytes) -> bool:
    """Is ``line`` (without ``\\r``) a well-formed slcan frame?"""
    if not line:
        return False
    kind = line[:1]
    if kind in (b"t", b"r", b"d", b"b"):
        id_len = 3
    elif kind in (b"T", b"R", b"D", b"B"):
        id_len = 8
    else:
        return False
    head = line[1:1 + id_len + 1]
    if len(head) != id_len + 1 or not _HEX.match(head):
        return False
    dlc = int(head[-1:], 16)
    if kind in (b"r", b"R"):
        return len(line) == 2 + id_len and dlc <= 8
    if kind in (b"t", b"T"):
        if dlc > 8:
            return False
        n = dlc
    else:
        n = _FD_DLC[dlc]
    data = line[2 + id_len:]
    return len(data) == 2 * n and bool(_HEX.match(data))


def line_length(extended: bool, remote: bool, n_data: int) -> int:
    """Bytes of the slcan line of a frame, its ``\\r`` included: the kind, the identifier (3 or 8
    hex digits), the DLC digit and two hex digits a data byte (none for a remote frame)."""
    return 1 + (8 if extended else 3) + 1 + (0 if remote else 2 * n_data) + 1


def make_raw_pty() -> tuple[int, int, str]:
    """A pseudo-terminal pair in raw mode: ``(master_fd, slave_fd, slave_path)``."""
    import tty

    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class _End:
    __slots__ = ("index", "master", "slave", "path", "buf", "open", "listen_only", "bitrate",
                 "out", "dropping")

    def __init__(self, index: int):
        self.index = index
        self.master, self.slave, self.path = make_raw_pty()
        os.set_blocking(self.master, False)
        self.buf = bytearray()
        self.out = bytearray()
        self.open = False
        self.listen_only = False
        self.bitrate: int | None = None
        self.dropping = False


class SlcanBridge:
    """Relay slcan frame lines between ``n`` pseudo-terminals (one CAN bus)."""

    def __init__(self, n: int = 2, max_pending: int = 1 << 20):
        if n < 2:
            raise ValueError("a bus needs at least two ends")
        self.ends = [_End(i) for i in range(n)]
        self.max_pending = max_pending
        self.frames_relayed = 0
        self.frames_dropped = 0
        self.frames_unheard = 0
        self.commands = 0
        self.bad_lines = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def paths(self) -> list[str]:
        return [e.path for e in self.ends]

    # lifecycle -------------------------------------------------------------
    def start(self) -> "SlcanBridge":
        if self._thread is None:
            self._thread = threading.Thread(target=self.run, name="slcan-bridge", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for e in self.ends:
            for fd in (e.master, e.slave):
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.ends = []

    def open_ends(self) -> int:
        """How many ends have opened their channel (``O``/``L``) and not closed it."""
        return sum(1 for e in self.ends if e.open)

    def wait_open(self, count: int | None = None, timeout: float = 2.0) -> bool:
        """Wait (bounded) until ``count`` ends (default: all) are open.

        Frames sent before the other ends have opened their channel are lost,
        as on a real bus; call this after opening the buses and before the
        first frame when nothing may be lost."""
        import time

        count = len(self.ends) if count is None else count
        deadline = time.monotonic() + timeout
        while self.open_ends() < count:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.001)
        return True

    def __enter__(self) -> "SlcanBridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def counters(self) -> dict:
        return {"frames_relayed": self.frames_relayed, "frames_dropped": self.frames_dropped,
                "frames_unheard": self.frames_unheard, "commands": self.commands, "bad_lines": self.bad_lines}

    # relay -------------------------------------------------------------------
    def run(self) -> None:
        """Relay until stopped: each end's readable bytes are read (one read each), their lines
        relayed into the other ends' output, then every end's output written in one write (a
        batch of frames costs a write per end, not one a frame)."""
        sel = selectors.DefaultSelector()
        for e in self.ends:
            sel.register(e.master, selectors.EVENT_READ, e)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=0.02):
                    self._read_end(key.data)
                for e in self.ends:
                    if e.out:
                        self._flush(e)
        finally:
            sel.close()

    def _read_end(self, e: _End) -> None:
        try:
            data = os.read(e.master, 65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        start = 0
        while True:
            cr = data.find(b"\r", start)
            if cr < 0:
                if not e.dropping:
                    e.buf += data[start:]
                    if len(e.buf) > MAX_LINE:
                        e.buf.clear()
                        e.dropping = True
                        self.bad_lines += 1
                return
            if e.dropping:
                e.dropping = False
                e.buf.clear()
            else:
                e.buf += data[start:cr]
                line = bytes(e.buf).strip(b"\n")
                e.buf.clear()
                self._line(e, line)
            start = cr + 1

    def _reply(self, e: _End, data: bytes) -> None:
        e.out += data
        self._flush(e)

    def _flush(self, e: _End) -> None:
        if len(e.out) > self.max_pending:        # nobody reads this end: drop the oldest
            del e.out[:len(e.out) - self.max_pending]
        try:
            n = os.write(e.master, e.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            e.out.clear()
            return
        del e.out[:n]

    def _line(self, e: _End, line: bytes) -> None:
        if not line:
            self._reply(e, b"\r")
            return
        c = line[:1]
        if c in b"tTrRdDbB":
            if not frame_line_ok(line):
                self.bad_lines += 1
                self._reply(e, b"\a")
                return
            if not e.open or e.listen_only:
                self.frames_dropped += 1
                self._reply(e, b"\a")
                return
            delivered = False
            for o in self.ends:
                if o is e or not o.open:
                    continue
                if e.bitrate is not None and o.bitrate is not None and e.bitrate != o.bitrate:
                    self.frames_dropped += 1     # different bit rates: no frame gets through
                    continue
                o.out += line + b"\r"         # written with the rest of this read's lines (run)
                delivered = True
            if delivered:
                self.frames_relayed += 1
            else:
                self.frames_unheard += 1
            return
        self.commands += 1
        cmd = line.decode("ascii", "replace")
        if cmd in ("O", "L"):
            e.open, e.listen_only = True, cmd == "L"
            self._reply(e, b"\r")
        elif cmd == "C":
            e.open = False
            self._reply(e, b"\r")
        elif cmd in SLCAN_BITRATES:
            e.bitrate = SLCAN_BITRATES[cmd]
            self._reply(e, b"\r")
        elif cmd == "V":
            self._reply(e, b"V1013\r")
        elif cmd == "N":
            self._reply(e, b"NCT%02d\r" % e.index)
        elif cmd == "F":
            self._reply(e, b"F00\r")
        elif cmd[:1] in ("s", "Y", "M", "m", "Z", "X", "U", "Q", "W"):
            self._reply(e, b"\r")
        else:
            self.bad_lines += 1
            self._reply(e, b"\a")


def main(argv=None) -> int:
    import argparse
    import signal
    import sys

    ap = argparse.ArgumentParser(prog="python -m coiltrack.protocol.slcan",
                                 description="slcan adapter emulator: one CAN bus over pseudo-terminals")
    ap.add_argument("--ends", type=int, default=2, help="number of bus ends (ptys), default 2")
    ap.add_argument("--exit-on-eof", action="store_true",
                    help="also stop when stdin reaches end of file (run under a parent's pipe)")
    args = ap.parse_args(argv)
    done = threading.Event()
    # the handlers before the paths: a parent may stop the bridge as soon as it has read them
    signal.signal(signal.SIGTERM, lambda *a: done.set())
    signal.signal(signal.SIGINT, lambda *a: done.set())
    bridge = SlcanBridge(args.ends)
    for p in bridge.paths:
        print(p)
    sys.stdout.flush()

    def watch_stdin():
        try:
            while sys.stdin.buffer.read1(4096):
                pass
        except (OSError, ValueError):
            pass
        done.set()

    if args.exit_on_eof:
        threading.Thread(target=watch_stdin, daemon=True).start()
    bridge.start()
    try:
        while not done.wait(0.2):
            pass
    finally:
        bridge.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
