"""The frames a flight controller speaks, against the node's: ``odom`` (REP-105: gravity-aligned, z up, x/y
east/north-like with the first clip's arbitrary yaw) to PX4's local NED/FRD frame, and the IMU body frame
``base_frame`` to the vehicle's FRD (PX4, MAVLink) and FLU (REP-103, MAVROS's ``base_link``) body frames.

A rotation ``R_AB`` [3,3] maps vectors in frame B to frame A. The local frame is odom with the ENU -> NED swap (x <-> y,
z negated): a flight north-east-up in an ENU-aligned odom has NED position (+, +, -). The vehicle's FRD axes are
named as signed axes of the IMU body frame (``frd_axes``, e.g. EuRoC's IMU: x up, y right, z forward gives
"+z,+y,-x").
"""

from __future__ import annotations

import numpy as np

#: R_NED_ENU: odom (x east, y north, z up) -> the local NED frame (x north, y east, z down); its own inverse.
NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: R_FLU_FRD: the vehicle's FRD body axes -> its FLU body axes (REP-103 ``base_link``); its own inverse.
FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])
#: Axes of a base frame that is FLU itself (REP-103 ``base_link``).
FLU_AXES = "+x,-y,-z"
_UNIT = {"x": 0, "y": 1, "z": 2}


def frd_rotation(axes: str) -> np.ndarray:
    """R_FRD_B [3,3] from ``axes``: the vehicle's forward, right and down axes as signed axes of the body frame B,
    comma-separated (``"+z,+y,-x"``: forward = +z of B, right = +y, down = -x). ValueError naming the problem when the
    text is not three signed axes forming a right-handed frame."""
    parts = [p.strip().lower() for p in str(axes).split(",")]
    if len(parts) != 3 or any(len(p) != 2 or p[0] not in "+-" or p[1] not in _UNIT for p in parts):
        raise ValueError(f"frd_axes {axes!r}: expected three signed axes of base_frame for forward, right and down, "
                         "e.g. '+x,-y,-z' (an FLU base frame) or '+z,+y,-x' (EuRoC's IMU)")
    R = np.zeros((3, 3))
    for row, p in enumerate(parts):
        R[row, _UNIT[p[1]]] = 1.0 if p[0] == "+" else -1.0
    if round(float(np.linalg.det(R))) != 1:
        raise ValueError(f"frd_axes {axes!r}: forward, right and down must be three different axes forming a "
                         "right-handed frame (forward x right = down)")
    return R


__all__ = ["FLU_AXES", "FLU_FROM_FRD", "NED_FROM_ENU", "frd_rotation"]
