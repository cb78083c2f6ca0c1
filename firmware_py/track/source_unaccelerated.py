"""The source's module with its orientation only: eq 6.8 without the source's
acceleration, for comparison.

Thesis ``002_cd7f1fdb7fc67471.txt`` eq 6.8: ``a_net = a_sensor - a_source``.
:class:`burst_fusion.SourceInertial` gives the fusion filter ``Phi`` and
``Phi f_source`` from the source's IMU (``burst_fusion.MeasuredForce``). With
:class:`Unaccelerated` as its ``force`` it keeps
``Phi`` from the same ch. 2 filter but hands the fusion ``Phi f_source = -g``
(``-gravity_mps2``, global frame, m/s^2), i.e. it treats the source as
unaccelerated: what a tracker that knows the source's orientation but not its
motion would do. Selected by ``body.source_acceleration = false``; the
body-worn scenarios' ``-noanet`` runs measure the difference on a moving
source.
"""
from __future__ import annotations


class Unaccelerated:
    """The ``force`` of :class:`burst_fusion.SourceInertial` (as ``burst_fusion.MeasuredForce``;
    this module needs nothing of burst_fusion's): the specific force stays ``-g`` (3,) m/s^2."""

    def update(self, P, fv, ax: float, ay: float, az: float) -> None:
        """The source taken as unaccelerated: ``Phi f_source`` stays ``-g`` (set at construction)."""
