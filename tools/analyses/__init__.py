"""Research analyses, each but ``perf_solvers`` and ``pulse_cost`` runnable as ``python -m coiltrack.tools.analyses.NAME``
(its docstring gives the command line and what it prints):

* ``energy_bound``: the least coil energy any pulse policy needs for the fixed cycle's accuracy
  (its pulse model, samples per pulse and the cost of information in a window: ``pulse_cost``);
* ``front_plot``: the energy-accuracy front against the fixed cycle with that bound on one figure;
* ``pareto``: energy against accuracy from ``coiltrack sweep --json`` files;
* ``gietler_edge``: divergences at the edge of Gietler's 2 m range;
* ``gietler_timing``: time per filter iteration against the paper's;
* ``raab_compare``: Raab's tracker beside the least-squares solve on the same runs;
* ``solver_budget``: work and time of the pose solver per solve, per unit and per tick;
* ``perf_solvers``: cost per update of the burst trackers' pose solvers (``coiltrack perf --solver``);
* ``recovery_table``: the recovery table of ``docs/faults.md`` on many seeds.
"""
