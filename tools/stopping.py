"""Stopping a run before its end, cleanly.

``coiltrack`` turns SIGINT and SIGTERM into :class:`Interrupted` (raised in
the main thread wherever the work is), so every command unwinds through its
``finally`` blocks: children are stopped, temporary files removed, and the
commands with a report write what was done, marked ``"interrupted": true``.
A second signal while the first is being handled stops at once.

A child process started with :func:`start_child` dies with its parent
(``PR_SET_PDEATHSIG`` on Linux), even if the parent is killed outright.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys

#: exit status of a firmware stopped because its peer went silent
EXIT_PEER_SILENT = 3
#: exit status when standard output was closed by the reader (``| head``): 128 + SIGPIPE
EXIT_BROKEN_PIPE = 141

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(BaseException):
    """The run ended before its duration; ``exit_code`` is the command's exit status.
    A BaseException, as KeyboardInterrupt: no ``except Exception`` on the way swallows it."""

    def __init__(self, reason: str, exit_code: int):
        super().__init__(reason)
        self.reason = reason
        self.exit_code = exit_code
        #: what the interrupted loop had measured, when it has something to give
        self.partial = None


class Interrupted(Stopped):
    """SIGINT or SIGTERM."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name, 128 + signum)
        self.signum = signum


class PeerSilent(Stopped):
    """Nothing arrived on the link for longer than allowed."""

    def __init__(self, silent_s: float):
        super().__init__(f"no bytes from the peer for {silent_s:g} s", EXIT_PEER_SILENT)


def _raise(signum, frame):
    for s in _SIGNALS:          # a second signal stops at once
        signal.signal(s, signal.SIG_DFL)
    raise Interrupted(signum)


@contextlib.contextmanager
def on_signals():
    """SIGINT and SIGTERM raise :class:`Interrupted` inside the block (main thread only)."""
    saved = {s: signal.getsignal(s) for s in _SIGNALS}
    for s in _SIGNALS:
        signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


@contextlib.contextmanager
def held_signals():
    """SIGINT and SIGTERM held back inside the block and delivered at its end. Start a
    child in one (``with held_signals(): child = start_child(cmd)``): a signal during the
    fork would be lost in the interpreter's after-fork hooks, and after the block the
    child is known to the caller, which can stop it."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _die_with_parent(parent: int):
    def setup() -> None:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _SIGNALS)
        if sys.platform.startswith("linux"):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)       # PR_SET_PDEATHSIG
        if os.getppid() != parent:                           # the parent died before prctl
            os._exit(1)
    return setup


def start_child(cmd: list[str], **popen) -> subprocess.Popen:
    """Start ``cmd`` (within :func:`held_signals`); it receives SIGTERM when this process
    dies, however it dies."""
    return subprocess.Popen(cmd, preexec_fn=_die_with_parent(os.getpid()), **popen)


def stop_child(child: subprocess.Popen, wait_s: float = 0.0, grace_s: float = 0.8) -> int:
    """Give a child ``wait_s`` to end by itself, then SIGTERM, then SIGKILL after
    ``grace_s``; its exit status."""
    try:
        return child.wait(timeout=wait_s) if wait_s > 0 else child.wait(timeout=0)
    except subprocess.TimeoutExpired:
        pass
    if child.poll() is None:
        child.terminate()
        try:
            child.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            child.kill()
    return child.wait()


def mark(rep: dict, exc: Stopped) -> Stopped:
    """Mark ``rep`` as the report of a run that ``exc`` stopped, and hand it to ``exc``."""
    rep["interrupted"] = True
    rep["stopped_by"] = exc.reason
    exc.partial = rep
    return exc
