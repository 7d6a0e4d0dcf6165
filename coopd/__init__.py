"""coopd: cooperative 3D occupancy mapping for drone swarms."""

__version__ = "0.1.0"
