"""Vehicle: the flight-controller link (MAVLink), odometry in the map frame, FC clock sync, pose buffer."""

from .clock import ClockEstimate, ClockSync
from .link import LinkConfig, VehicleLink
from .odometry import OdometryLimits, OdometryTracker
from .pose_buffer import PoseBuffer, PoseLookupError, PoseSample, slerp
from .transport import parse_connection

__all__ = [
    "ClockEstimate",
    "ClockSync",
    "LinkConfig",
    "OdometryLimits",
    "OdometryTracker",
    "PoseBuffer",
    "PoseLookupError",
    "PoseSample",
    "VehicleLink",
    "parse_connection",
    "slerp",
]
