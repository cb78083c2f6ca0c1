"""An in-process CAN bus: a python-can ``BusABC`` whose ends, joined by one :class:`InprocChannel`,
hear every frame the others send, in order, and not their own (as python-can's ``virtual``).

It is what ``coiltrack bench --transport can`` puts between the firmware and the emulated nodes
on the simulated clock. python-can's ``virtual`` bus deep-copies each frame sent into each
receiver's locked queue (12.7 us a frame here, best of 5, CPU time) and passes each received
one through ``BusABC.recv``'s filter and log calls (2.2 us): the firmware's tick paid that for
every frame, 1.1 ms in a tick that sends three POSEs and sixteen PULSE_WINDOWs' frames, which a
board's CAN driver (a TX mailbox written, a RX FIFO read) does not cost. Here a frame sent is
one ``can.Message`` built per receiver (:func:`protocol.interfaces.message`; its own ``data``, the
sender's object never shared)
appended to that receiver's deque, and ``recv(timeout=0)`` pops it (the filters applied when
set). Blocking receives (``timeout`` > 0 or None, another thread sending) take ``BusABC``'s
general path. Frames keep python-can's fields: ``timestamp`` (the wall clock at ``send``, as
``virtual``), ``channel``, ``is_rx``.
"""
from __future__ import annotations

import threading
import time
from collections import deque

import can

from . import message

__all__ = ["InprocBus", "InprocChannel", "inproc_bus_pair"]


class InprocChannel:
    """The wire that joins :class:`InprocBus` ends (no registry by name: the ends share this object)."""

    def __init__(self, name: str = "inproc"):
        self.name = name
        self.ends: list[InprocBus] = []


class InprocBus(can.BusABC):
    """One end of an :class:`InprocChannel` (see the module docstring)."""

    def __init__(self, channel: InprocChannel, receive_own_messages: bool = False, rx_queue_size: int = 0,
                 **kwargs):
        super().__init__(channel=channel.name, **kwargs)
        self.channel_info = f"coiltrack in-process bus '{channel.name}'"
        self.wire = channel
        self.receive_own_messages = receive_own_messages
        self.rx_queue_size = rx_queue_size
        self._rx: deque = deque()
        self._cond = threading.Condition()
        self._waiting = False
        self._open = True
        #: frames dropped because this end's queue was full (``rx_queue_size`` > 0)
        self.overruns = 0
        channel.ends.append(self)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._open:
            raise can.CanOperationError("the bus is shut down")
        ts = time.time()
        for o in self.wire.ends:
            if o is self and not self.receive_own_messages:
                continue
            o._put(message(msg.arbitration_id, msg.is_extended_id, msg.data, msg.is_fd, msg.bitrate_switch, ts,
                           msg.is_remote_frame, msg.dlc, o is not self, self.wire.name, msg.is_error_frame,
                           msg.error_state_indicator))

    def _put(self, m: can.Message) -> None:
        if self.rx_queue_size and len(self._rx) >= self.rx_queue_size:
            self.overruns += 1
            return
        self._rx.append(m)
        if self._waiting:
            with self._cond:
                self._cond.notify_all()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """``BusABC.recv``, the frames waiting first: the first one that passes the filters (every
        frame without filters; those that do not pass are dropped), None when none does and
        ``timeout`` is 0 (``BusABC.recv`` gives None there as soon as one does not pass)."""
        rx = self._rx
        if self._filters is None:
            if rx:
                return rx.popleft()
        else:
            while rx:
                m = rx.popleft()
                if self._matches_filters(m):
                    return m
        if timeout == 0:
            return None
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None):
        if self._rx:
            return self._rx.popleft(), False
        if timeout is not None and timeout <= 0:
            return None, False
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            self._waiting = True
            try:
                while not self._rx:
                    left = None if deadline is None else deadline - time.monotonic()
                    if left is not None and left <= 0:
                        return None, False
                    self._cond.wait(left)
            finally:
                self._waiting = False
        return self._rx.popleft(), False

    def pending(self) -> int:
        """Frames waiting to be received."""
        return len(self._rx)

    def shutdown(self) -> None:
        if self._open:
            self._open = False
            if self in self.wire.ends:
                self.wire.ends.remove(self)
        super().shutdown()


def inproc_bus_pair(name: str = "inproc") -> tuple[InprocBus, InprocBus]:
    """Two ends of a fresh in-process bus."""
    ch = InprocChannel(name)
    return InprocBus(ch), InprocBus(ch)
