"""Camera: depth-frame sources (camera socket protocol, RealSense) feeding a newest-wins slot."""

from .frame import DepthFrame
from .protocol import FrameHeader, ProtocolError, parse_header
from .realsense import CameraUnavailable, RealSenseConfig, RealSenseSource, load_pyrealsense2
from .slot import LatestSlot
from .socket_source import SocketDepthSource, SocketSourceConfig

__all__ = [
    "CameraUnavailable",
    "DepthFrame",
    "FrameHeader",
    "LatestSlot",
    "ProtocolError",
    "RealSenseConfig",
    "RealSenseSource",
    "SocketDepthSource",
    "SocketSourceConfig",
    "load_pyrealsense2",
    "parse_header",
]
