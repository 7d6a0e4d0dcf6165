"""MAVLink NED/FRD to map ENU/FLU: the only place in coopd where these conventions meet."""

import numpy as np

from ..geometry import matrix_to_quat, quat_to_matrix

# x<->y swap and z flip: maps NED vectors to ENU and back (its own inverse, a reflection).
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# Body FRD <-> FLU: y and z flip (its own inverse).
FRD_FROM_FLU = np.diag([1.0, -1.0, -1.0])


def ned_to_enu(v) -> np.ndarray:
    """A position or vector in a NED-like local frame expressed in its ENU-like counterpart."""
    return ENU_FROM_NED @ np.asarray(v, dtype=np.float64).reshape(3)


def frd_in_ned_to_flu_in_enu(q_ned_frd) -> np.ndarray:
    """Attitude quaternion (w, x, y, z) of body FRD in NED to body FLU in ENU (R' = S R F)."""
    r = ENU_FROM_NED @ quat_to_matrix(q_ned_frd) @ FRD_FROM_FLU
    return matrix_to_quat(r)


def flu_in_enu_to_frd_in_ned(q_enu_flu) -> np.ndarray:
    """Inverse of frd_in_ned_to_flu_in_enu (for tests and for sending setpoints)."""
    r = ENU_FROM_NED @ quat_to_matrix(q_enu_flu) @ FRD_FROM_FLU
    return matrix_to_quat(r)
