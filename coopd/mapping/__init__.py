"""Mapping: depth frames and camera poses in, HIMM updates of the local occupancy grid out."""

from .mapper import IntegrationStats, Mapper, MapperConfig, load_kernels
from .sensor import CameraMount, FrameRejected, Intrinsics, Pose, check_depth

__all__ = ["CameraMount", "FrameRejected", "IntegrationStats", "Intrinsics", "Mapper", "MapperConfig",
           "Pose", "check_depth", "load_kernels"]
