"""The bench engine: what joins a firmware and the emulated world on a link and runs them.

* ``runner``: one run in process on the simulated clock (``BenchSetup``, ``run_inproc``);
* ``realtime``: the wall-clock loops, and the two-process bench over a pseudo-terminal (``run_pty``);
* ``timing``: tick timing figures; ``links``, ``linktap``: byte links and taps on them;
* ``framelog``: frame logs recorded and replayed; ``work_classes``: what each tick did;
* ``sweep``, ``check``, ``soak``: many runs (Monte Carlo sweeps, robustness sweep, soak);
* ``gietler``: Gietler et al.'s measurement-level run path (no protocol bench);
* ``alloc``: the counter of numpy allocations (``coiltrack perf`` and the allocation tests).
"""
