"""Count numpy array-data allocations: the proof that a firmware tick allocates none.

numpy (>= 1.22) takes its array-data allocator from a handler object
(NEP 49, ``PyDataMem_SetHandler``). :class:`NumpyAllocationCounter` installs a
handler that counts every ``malloc``, ``calloc`` and ``realloc`` of array
data and forwards it to numpy's default allocator; ``free`` is numpy's own
(C) function, so memory is released identically whether or not counting is
on. Every array numpy creates, a temporary of one element included (a Python
float used as a ufunc operand becomes a 0-d array), goes through one of these
calls, so a count of zero over a block of code means that block created no
array data. Views (slices, transposes) share data and are not counted.

The handler is reached through numpy's C-API table (``_ARRAY_API``, the
entries ``PyDataMem_SetHandler`` and ``PyDataMem_DefaultHandler``) with
ctypes; nothing is compiled. :func:`available` says whether this numpy
exposes them; callers fall back to tracemalloc (domain
``numpy.lib.tracemalloc_domain``) otherwise.

Use::

    counter = NumpyAllocationCounter()
    with counter:
        fw.tick(t)
    assert counter.count == 0
"""
from __future__ import annotations

import ctypes
import sys
import tracemalloc

import numpy as np

_MALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_CALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)
_REALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
# the default allocator's functions are called with the GIL held (they may release it themselves)
_PMALLOC = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_PCALLOC = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)
_PREALLOC = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)

_SET_HANDLER_INDEX = 304        # PyDataMem_SetHandler in numpy's C-API table (>= 1.22)
_DEFAULT_HANDLER_INDEX = 306    # PyDataMem_DefaultHandler


class _Allocator(ctypes.Structure):
    _fields_ = [("ctx", ctypes.c_void_p), ("malloc", ctypes.c_void_p), ("calloc", ctypes.c_void_p),
                ("realloc", ctypes.c_void_p), ("free", ctypes.c_void_p)]


class _Handler(ctypes.Structure):
    _fields_ = [("name", ctypes.c_char * 127), ("version", ctypes.c_uint8), ("allocator", _Allocator)]


_state: dict = {}


def _setup():
    """Build the counting handler once per process (kept alive for good:
    arrays allocated under it hold a reference and free through it)."""
    if _state:
        return _state
    api = ctypes.pythonapi
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    api.PyCapsule_New.restype = ctypes.py_object
    api.PyCapsule_New.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
    core = getattr(np, "_core", None) or np.core
    table = api.PyCapsule_GetPointer(core._multiarray_umath._ARRAY_API, None)
    ptrs = ctypes.cast(table, ctypes.POINTER(ctypes.c_void_p))
    set_handler = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.py_object)(ptrs[_SET_HANDLER_INDEX])
    default_cap = ctypes.cast(ptrs[_DEFAULT_HANDLER_INDEX], ctypes.POINTER(ctypes.py_object))[0]
    dh = ctypes.cast(api.PyCapsule_GetPointer(default_cap, b"mem_handler"), ctypes.POINTER(_Handler))[0]
    if dh.version != 1:
        raise RuntimeError(f"unsupported numpy memory handler version {dh.version}")
    d_malloc = _PMALLOC(dh.allocator.malloc)
    d_calloc = _PCALLOC(dh.allocator.calloc)
    d_realloc = _PREALLOC(dh.allocator.realloc)
    counts = [0, 0]          # calls, bytes
    stacks = []              # where allocations happened, when a counter asks for it
    record = [False]

    def _note():
        if record[0]:
            import traceback
            stacks.append(traceback.extract_stack(limit=12)[:-2])

    def _m(ctx, size):
        counts[0] += 1
        counts[1] += size
        _note()
        return d_malloc(ctx, size)

    def _c(ctx, nelem, elsize):
        counts[0] += 1
        counts[1] += nelem * elsize
        _note()
        return d_calloc(ctx, nelem, elsize)

    def _r(ctx, ptr, size):
        counts[0] += 1
        counts[1] += size
        _note()
        return d_realloc(ctx, ptr, size)

    cbs = (_MALLOC(_m), _CALLOC(_c), _REALLOC(_r))
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    mem = libc.malloc(ctypes.sizeof(_Handler))          # never freed: arrays point at it
    h = _Handler.from_address(mem)
    h.name = b"coiltrack_counting_allocator"
    h.version = 1
    h.allocator.ctx = dh.allocator.ctx
    h.allocator.malloc = ctypes.cast(cbs[0], ctypes.c_void_p).value
    h.allocator.calloc = ctypes.cast(cbs[1], ctypes.c_void_p).value
    h.allocator.realloc = ctypes.cast(cbs[2], ctypes.c_void_p).value
    h.allocator.free = dh.allocator.free
    capsule = api.PyCapsule_New(mem, b"mem_handler", None)
    for obj in (*cbs, capsule):                      # immortal: see the docstring
        api.Py_IncRef(ctypes.py_object(obj))
    _state.update(set_handler=set_handler, capsule=capsule, counts=counts, cbs=cbs,
                  keep=(d_malloc, d_calloc, d_realloc), stacks=stacks, record=record)
    return _state


def available() -> bool:
    """True when numpy's handler API can be reached (numpy >= 1.22, CPython)."""
    try:
        _setup()
        return True
    except Exception:       # pragma: no cover - depends on the numpy build
        return False


class NumpyAllocationCounter:
    """Context manager counting numpy array-data allocations made inside it.

    ``count`` and ``bytes`` accumulate over every ``with`` block until
    :meth:`reset`. Blocks may not nest. With ``record_stacks`` the Python
    stack of every allocation is kept in ``stacks`` (for diagnostics).
    """

    def __init__(self, record_stacks: bool = False):
        st = _setup()
        self._set = st["set_handler"]
        self._cap = st["capsule"]
        self._counts = st["counts"]
        self._record = st["record"]
        self._stacks = st["stacks"]
        self.record_stacks = record_stacks
        self.stacks: list = []
        self._prev = None
        self.count = 0
        self.bytes = 0
        self._c0 = 0
        self._b0 = 0

    def reset(self) -> None:
        self.count = 0
        self.bytes = 0
        self.stacks = []

    def __enter__(self):
        self._c0 = self._counts[0]
        self._b0 = self._counts[1]
        if self.record_stacks:
            self._stacks.clear()
            self._record[0] = True
        self._prev = self._set(self._cap)
        return self

    def __exit__(self, *exc):
        self._set(self._prev)
        self._prev = None
        if self.record_stacks:
            self._record[0] = False
            self.stacks.extend(self._stacks)
            self._stacks.clear()
        self.count += self._counts[0] - self._c0
        self.bytes += self._counts[1] - self._b0
        return False


# ---------------------------------------------------------------------------
# tracemalloc-based checks (independent of the handler)
# ---------------------------------------------------------------------------
NUMPY_DOMAIN = tracemalloc.DomainFilter(True, np.lib.tracemalloc_domain)


_DOMAIN = np.lib.tracemalloc_domain


def numpy_traces() -> int:
    """Number of live numpy-domain blocks tracemalloc knows of (must be tracing)."""
    get = getattr(tracemalloc, "_get_traces", None)
    if get is None:                          # pragma: no cover - other Python implementations
        return len(tracemalloc.take_snapshot().filter_traces([NUMPY_DOMAIN]).traces)
    n = 0
    for tr in get():
        if tr[0] == _DOMAIN:
            n += 1
    return n


def numpy_blocks_alive_during(fn) -> int:
    """Largest number of numpy-domain blocks allocated while ``fn`` runs and
    found alive before any bytecode instruction of ``fn`` or of what it calls
    (``sys.settrace`` with opcode events; a temporary array sits at least on
    the value stack until the next instruction). Slow: the live traces are
    counted at every opcode (tracemalloc is restarted for the call, so only
    what the call allocates is traced)."""
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    base = numpy_traces()
    peak = 0

    def local(frame, event, arg):
        nonlocal peak
        c = numpy_traces() - base
        if c > peak:
            peak = c
        return local

    def on_call(frame, event, arg):
        frame.f_trace_opcodes = True
        return local(frame, event, arg)

    old = sys.gettrace()
    sys.settrace(on_call)
    try:
        fn()
    finally:
        sys.settrace(old)
        c = numpy_traces() - base
        peak = max(peak, c)
        if not was_tracing:
            tracemalloc.stop()
    return peak
