"""Small rotation helpers (numpy only, allocation-free where it matters).

Conventions: a rotation matrix ``R`` maps sensor-frame vectors to the source
frame (``v_source = R @ v_sensor``); quaternions are ``(w, x, y, z)``,
Hamilton convention, unit norm, ``w >= 0``.
"""
from __future__ import annotations

import math

import numpy as np


def quat_from_matrix(R, out=None):
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    q = np.empty(4) if out is None else out
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0.0:
        s = math.sqrt(t + 1.0) * 2.0
        q[0] = 0.25 * s
        q[1] = (R[2, 1] - R[1, 2]) / s
        q[2] = (R[0, 2] - R[2, 0]) / s
        q[3] = (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2.0
        q[0] = (R[2, 1] - R[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (R[0, 1] + R[1, 0]) / s
        q[3] = (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2.0
        q[0] = (R[0, 2] - R[2, 0]) / s
        q[1] = (R[0, 1] + R[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2.0
        q[0] = (R[1, 0] - R[0, 1]) / s
        q[1] = (R[0, 2] + R[2, 0]) / s
        q[2] = (R[1, 2] + R[2, 1]) / s
        q[3] = 0.25 * s
    if q[0] < 0.0:
        q *= -1.0
    q /= math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return q


def quat_from_elements(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Unit quaternion (w, x, y, z), ``w >= 0``, of the rotation matrix with
    these elements, as Python floats (Shepperd's method, as
    :func:`quat_from_matrix`, with no array allocated)."""
    t = r00 + r11 + r22
    if t > 0.0:
        s = math.sqrt(t + 1.0) * 2.0
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = math.sqrt(1.0 + r00 - r11 - r22) * 2.0
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = math.sqrt(1.0 + r11 - r00 - r22) * 2.0
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = math.sqrt(1.0 + r22 - r00 - r11) * 2.0
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


def quat_tuple(R):
    """:func:`quat_from_elements` of a (3, 3) array."""
    return quat_from_elements(float(R[0, 0]), float(R[0, 1]), float(R[0, 2]),
                              float(R[1, 0]), float(R[1, 1]), float(R[1, 2]),
                              float(R[2, 0]), float(R[2, 1]), float(R[2, 2]))


def matrix_from_quat(q, out=None):
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    R = np.empty((3, 3)) if out is None else out
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_angle(R) -> float:
    """The angle (rad) of the rotation matrix ``R`` (3, 3): ``acos((tr R - 1) / 2)``, clamped."""
    c = (float(R[0, 0]) + float(R[1, 1]) + float(R[2, 2]) - 1.0) * 0.5
    return math.acos(max(-1.0, min(1.0, c)))


def angle_between(Ra, Rb) -> float:
    """Smallest rotation angle (rad) taking frame ``Ra`` onto ``Rb``."""
    return rotation_angle(Ra.T @ Rb)
