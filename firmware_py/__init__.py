"""coiltrack firmware: what runs on the board.

A fixed-step, allocation-free loop (:mod:`coiltrack.firmware.loop`) built from
stages with one job each:

- ``model/``     coil fields (exact loop by AGM, dipole) and their Jacobians;
                 the one signal model ``h = R^T B(p)``, ``H`` (``model/signal.py``)
- ``measure/``   sample rings and pulse-window extraction
- ``pose/``      closed-form start, least-squares pose, Cramer-Rao bound; the
                 numpy reference solver the tests compare against lives apart
                 in ``pose/reference.py``
- ``estimate/``  state layouts, the one Kalman update, orientation filter,
                 magnetic-inertial filter, single-coil EKF, smoother
- ``actuate/``   excitation policies (fixed cycle, adaptive single coil)
- ``track/``     trackers that turn measurements into poses
- ``supervise/`` time sync, node health, magnetometer flips

The public functional API (field models, closed form, reference solver) is
importable from here.
"""
from coiltrack.firmware.model.field import (Coil, CoilSet, dipole_field, dipole_jacobian, loop_field,
                                            loop_jacobian, orthogonal_source)
from coiltrack.firmware.pose.reference import crlb, crlb_position_rms, kuipers, solve_pose

__all__ = ["Coil", "CoilSet", "dipole_field", "dipole_jacobian", "loop_field", "loop_jacobian",
           "orthogonal_source", "kuipers", "solve_pose", "crlb", "crlb_position_rms"]
