"""Outputs for other tools, shared by ``bench``, ``firmware`` and ``emulator``:
``--igtl`` (``tools.outputs.igtl``), ``--capture`` (``tools.outputs.buscapture``), and on the
bench ``--poses`` (``tools.outputs.posecsv``) and ``--plot`` (``tools.outputs.plot``).

:meth:`Outputs.open` checks every argument and output path and opens the
server and the capture file before any work; the runners then call
:meth:`Outputs.wrap` on the link to tap, :meth:`Outputs.tick` every tick of a
simulated clock (which paces it to the wall clock while poses are served)
and :meth:`Outputs.finish` with the bench and the report at the end.
"""
from __future__ import annotations

import math
import os
import time
from ..bench.linktap import TapPort


class OutputError(ValueError):
    """A bad output argument: the message names it and what it accepts."""


def add_igtl_arguments(p) -> None:
    p.add_argument("--igtl", type=int, metavar="PORT", default=None,
                   help="serve every valid pose as an OpenIGTLink TRANSFORM, millimetres, Unix time stamps, on this "
                        "TCP port (0..65535; 0 takes a free one), for 3D Slicer or PLUS: device Sensor<node>ToSource "
                        "the node's track (fused when it fuses), Sensor<node>MagToSource its magnetic poses")
    p.add_argument("--igtl-host", default="127.0.0.1", help="address the OpenIGTLink server binds (default 127.0.0.1)")
    p.add_argument("--igtl-wait", type=float, default=0.0, metavar="S",
                   help="wait up to S seconds (0..3600) for an OpenIGTLink client before starting")


def add_capture_argument(p) -> None:
    p.add_argument("--capture", metavar="PATH",
                   help="record what crosses the link: on CAN a python-can log by suffix (.blf, .asc, .log), "
                        "on serial raw bytes (e.g. .bin); read back by `coiltrack decode`")


def add_file_arguments(p) -> None:
    p.add_argument("--poses", metavar="PATH", help="write one CSV row per pose, magnetic and fused, with the truth, "
                                                  "errors, status and covariance diagonal")
    p.add_argument("--plot", metavar="PATH", help="write a PNG: trajectory (xy, xz, yz), error against time, error "
                                                 "against range with the CRLB")


def add_bench_arguments(p) -> None:
    add_igtl_arguments(p)
    add_capture_argument(p)
    add_file_arguments(p)


def open_or_exit(command: str, args, can_link: bool = False) -> "Outputs":
    """:meth:`Outputs.open` and :meth:`Outputs.start` for ``coiltrack COMMAND``; a bad
    argument is one line on stderr and exit status 2."""
    import sys

    try:
        out = Outputs.open(args, can_link)
    except OutputError as exc:
        print(f"coiltrack {command}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    out.start()
    return out


def check_writable(arg: str, path: str) -> None:
    """Raise :class:`OutputError` unless a file can be written at ``path``."""
    d = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise OutputError(f"{arg}: '{path}' is a directory; give a file path")
    if not os.path.isdir(d):
        raise OutputError(f"{arg}: directory '{d}' does not exist")
    if not os.access(d, os.W_OK):
        raise OutputError(f"{arg}: cannot write in '{d}'")


class Outputs:
    """What one command was asked to produce; see the module docstring."""

    def __init__(self, args):
        self.igtl_port = getattr(args, "igtl", None)
        self.igtl_host = getattr(args, "igtl_host", "127.0.0.1")
        self.igtl_wait = getattr(args, "igtl_wait", 0.0) or 0.0
        self.capture_path = getattr(args, "capture", None)
        self.poses_path = getattr(args, "poses", None)
        self.plot_path = getattr(args, "plot", None)
        self.igtl = None
        self.capture = None
        self.capture_kind = None
        self.now_us = 0
        self._wall0 = None

    @classmethod
    def open(cls, args, can_link: bool = False) -> "Outputs":
        """Check the arguments and paths (``can_link``: the link to capture is a CAN bus)
        and start the OpenIGTLink server; raises :class:`OutputError`."""
        out = cls(args)
        out._check(can_link)
        if out.igtl_port is not None:
            try:
                from .igtl import IgtlOutput
            except ImportError:
                raise OutputError("--igtl: needs pyigtl (pip install 'coiltrack[bench]')") from None
            try:
                out.igtl = IgtlOutput(out.igtl_host, out.igtl_port)
            except OSError as exc:
                raise OutputError(f"--igtl: cannot serve on {out.igtl_host}:{out.igtl_port}: {exc.strerror or exc}")
        return out

    def _check(self, can_link: bool) -> None:
        if self.igtl_port is not None and not 0 <= self.igtl_port <= 65535:
            raise OutputError(f"--igtl: port must be 0..65535 (got {self.igtl_port})")
        if not (math.isfinite(self.igtl_wait) and 0 <= self.igtl_wait <= 3600):
            raise OutputError(f"--igtl-wait: seconds must be 0..3600 (got {self.igtl_wait})")
        for arg, path in (("--capture", self.capture_path), ("--poses", self.poses_path), ("--plot", self.plot_path)):
            if path:
                check_writable(arg, path)
        if self.capture_path:
            from .buscapture import check_path

            why = check_path(self.capture_path, can_link)
            if why:
                raise OutputError(f"--capture: {why}")
        if self.plot_path:
            try:
                import matplotlib  # noqa: F401
            except ImportError:
                raise OutputError("--plot: needs matplotlib (pip install 'coiltrack[bench]')") from None
            from .plot import written_path

            try:
                written = written_path(self.plot_path)
            except ValueError as exc:
                raise OutputError(f"--plot: {exc}") from None
            check_writable("--plot", written)

    @property
    def paced(self) -> bool:
        """Serving poses: a simulated clock follows the wall clock."""
        return self.igtl is not None

    def wrap(self, link, side: str = "firmware", clock_us=None):
        """Tap ``link`` (the firmware's port, or the emulator's link: ``side``); opens the
        capture. ``clock_us()`` stamps CAN frames (default: the time of :meth:`tick`)."""
        wall_clock = clock_us is not None
        clock_us = clock_us or (lambda: self.now_us)
        rx, tx = [], []
        if self.capture_path and hasattr(link, "bus"):
            from .buscapture import CanCapture

            self.capture, self.capture_kind = CanCapture(self.capture_path, link, clock_us), "can"
        elif self.capture_path:
            from .buscapture import RawCapture

            self.capture, self.capture_kind = RawCapture(self.capture_path), "serial"
            rx.append(self.capture.rx)
            tx.append(self.capture.tx)
        if self.igtl is not None:
            # POSE frames leave the firmware's port and arrive on the emulator's link
            (tx if side == "firmware" else rx).append(self.igtl.feed)
            if wall_clock:      # the master clock runs on the wall clock: map it to Unix time now
                self.igtl.anchor(clock_us())
        return TapPort(link, rx, tx) if rx or tx else link

    def start(self, log=print) -> None:
        """Before the run: say where poses are served and wait for a client (``--igtl-wait``)."""
        if self.igtl is None:
            return
        log(f"OpenIGTLink: serving poses on {self.igtl.address}", flush=True)
        if self.igtl_wait > 0 and not self.igtl.wait_for_client(self.igtl_wait):
            log(f"OpenIGTLink: no client after {self.igtl_wait:g} s; starting anyway", flush=True)

    def tick(self, t_us: int) -> None:
        """Simulated time ``t_us`` is about to run; paced to the wall clock when serving."""
        self.now_us = t_us
        if not self.paced:
            return
        now = time.perf_counter()
        if self._wall0 is None:
            self._wall0 = now - t_us * 1e-6
            self.igtl.anchor(t_us)      # the simulated master clock follows the wall clock from here
        ahead = self._wall0 + t_us * 1e-6 - now
        if ahead > 0.002:
            time.sleep(ahead)

    def finish(self, bench=None, rep: dict | None = None) -> None:
        """Write the pose table and the figure (``bench`` and its report), close the rest,
        and note in ``rep`` what was written."""
        rep = rep if rep is not None else {}
        if self.poses_path or self.plot_path:
            from .posecsv import pose_table, write_csv

            table = pose_table(bench.recorder.poses)
            if self.poses_path:
                write_csv(table, self.poses_path)
                rep["poses_csv"] = self.poses_path
            if self.plot_path:
                from .plot import plot_run

                rep["plot"] = plot_run(self.plot_path, table, rep)     # the name written (.png added)
        self.close()
        if self.capture_path:
            rep["capture"] = {"path": self.capture_path, "kind": self.capture_kind}
        if self.igtl is not None:
            rep.update(self.igtl.counters())

    @staticmethod
    def say_written(rep: dict) -> None:
        """Tell what :meth:`finish` wrote."""
        for key, what in (("poses_csv", "pose table"), ("plot", "figure")):
            if rep.get(key):
                print(f"{what} written to {rep[key]}")
        if "capture" in rep:
            print(f"capture ({rep['capture']['kind']}) written to {rep['capture']['path']}")
        if "igtl_sent" in rep:
            per = ", ".join(f"{n} {k}" for n, k in rep.get("igtl_devices", {}).items())
            print(f"OpenIGTLink: {rep['igtl_sent']} transforms sent on {rep['igtl_address']}"
                  + (f" ({per})" if per else ""))

    def close(self) -> None:
        """Stop the server and finish the capture file (idempotent)."""
        if self.capture is not None:
            self.capture.close()
            self.capture = None
        if self.igtl is not None:
            self.igtl.close()
