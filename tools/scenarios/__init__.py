"""The registry of named scenarios: each family of scenarios is a module of this package,
listed in :data:`FAMILIES`; :data:`SCENARIOS` joins their scenarios by name and
:data:`EXPERIMENTS` the measurement-level experiments among them (``coiltrack sweep``).

A family module defines its scenarios (``SCENARIOS``, a :class:`~.base.Family`) and, where
some are experiments rather than bench runs, ``EXPERIMENTS`` (name -> :class:`~.base.Experiment`);
it registers nothing itself. A new family is a new module added to :data:`FAMILIES`.
"""
from __future__ import annotations

import argparse

from . import ac, adaptive, body, distortion, gietler, imperfect, multi, raab, thesis
from .base import Experiment, Scenario, SensorSpec

__all__ = ["FAMILIES", "SCENARIOS", "EXPERIMENTS", "Scenario", "SensorSpec", "Experiment", "get", "known",
           "listing"]

#: the scenario families, in the order their scenarios are listed
FAMILIES = (
    thesis,         # Roetenberg's bench and fusion runs, Schepers' adaptive actuation and their variants
    multi,          # multi16: many sensors on one bus
    body,           # body-worn rows of Tables 5.1 / 6.1
    raab,           # raab-acquire, helix-hemisphere
    ac,             # AC excitation: raab-ac, ac-vs-dc-metal
    adaptive,       # schepers-fixed-*
    gietler,        # Gietler et al. 2019: Tables I, IV-VII (sweep experiments)
    imperfect,      # imperfect-bench, imperfect-fusion
    distortion,     # steel-table: static metal, the distortion survey
)


def _join(families) -> tuple[dict[str, Scenario], dict[str, Experiment]]:
    scenarios: dict[str, Scenario] = {}
    experiments: dict[str, Experiment] = {}
    for fam in families:
        for s in fam.SCENARIOS:
            if s.name in scenarios:
                raise ValueError(f"scenario '{s.name}' of {fam.__name__} is already defined")
            scenarios[s.name] = s
        for name, exp in getattr(fam, "EXPERIMENTS", {}).items():
            if name not in scenarios:
                raise ValueError(f"experiment '{name}' of {fam.__name__} names no scenario of it")
            experiments[name] = exp
    return scenarios, experiments


#: scenario name -> :class:`Scenario`
SCENARIOS: dict[str, Scenario]
#: scenario name -> its :class:`Experiment` (a measurement-level experiment, run by ``coiltrack sweep``)
EXPERIMENTS: dict[str, Experiment]
SCENARIOS, EXPERIMENTS = _join(FAMILIES)


def get(name: str) -> Scenario:
    """The scenario ``name`` (KeyError naming the known ones otherwise)."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise KeyError(f"unknown scenario '{name}'; known: {', '.join(sorted(SCENARIOS))}") from None


def known(text: str) -> str:
    """A registered scenario name (an argparse type: ``--scenario``)."""
    if text not in SCENARIOS:
        raise argparse.ArgumentTypeError(f"unknown scenario '{text}' (known: {', '.join(sorted(SCENARIOS))})")
    return text


def listing() -> str:
    """One line per scenario, for a ``--help`` epilog."""
    w = max(len(n) for n in SCENARIOS)
    return "scenarios:\n" + "\n".join(f"  {n:<{w}}  {s.summary or s.description}" for n, s in sorted(SCENARIOS.items()))
