"""What the vehicle's estimator reports: its own local frame, a slow seeded drift and white noise."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from firmware_sim.frames import rot_z

EARTH_RADIUS_M = 6378137.0
WORLD_ORIGIN_LLA = (47.397742, 8.545594, 488.0)  # PX4 SITL's default home, mapped to world (0, 0, 0)


@dataclass(frozen=True)
class NoiseConfig:
    """Odometry error model: white noise on each report plus a slow drift of the estimate's frame
    (drift rates per second of flight: a disarmed vehicle at rest does not drift, see OdometryModel)."""

    pos_sigma_m: float = 0.01
    vel_sigma_m_s: float = 0.02
    att_sigma_rad: float = 0.003
    drift_xy_m_s: float = 0.001
    drift_z_m_s: float = 0.001
    drift_yaw_rad_s: float = 0.0001


NOISE_PRESETS = {
    "none": NoiseConfig(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "default": NoiseConfig(),
    "high": NoiseConfig(0.03, 0.05, 0.01, 0.015, 0.003, 0.002),
}


class OdometryModel:
    """Maps true world state to the vehicle's estimate in its reporting frame (ENU-like, origin o, yaw)."""

    def __init__(self, frame_origin, frame_yaw: float, noise: NoiseConfig, rng: np.random.Generator):
        """Draw this vehicle's drift once from its own generator; noise gets a generator of its own."""
        self.origin = np.asarray(frame_origin, float)
        self.frame_yaw = float(frame_yaw)
        self.frame_rot = rot_z(frame_yaw)
        self.reset_counter = 0
        """ODOMETRY.reset_counter: counts position resets of the running estimator (0 after a boot)."""
        self.frame_log: list[tuple[float, np.ndarray, float]] = [(0.0, self.origin.copy(), self.frame_yaw)]
        """(sim time, origin, frame yaw) of every reporting frame the estimator used, oldest first."""
        self.noise = noise
        self.drift_vel = np.array(
            [
                rng.normal(0, 1) * noise.drift_xy_m_s,
                rng.normal(0, 1) * noise.drift_xy_m_s,
                rng.normal(0, 1) * noise.drift_z_m_s,
            ]
        )
        self.drift_yaw_rate = float(rng.normal(0, 1) * noise.drift_yaw_rad_s)
        self._noise_rng = np.random.default_rng(rng.integers(1 << 62))
        self._drift_cache: tuple = (None, None, None)
        self._breaks: list[tuple[float, float, bool]] = [(0.0, 0.0, True)]
        """(sim time, drift time at it, drifting after it): one entry per change; drifting by default."""
        self._break_times = [0.0]

    def set_drifting(self, t: float, drifting: bool) -> None:
        """From sim time t on, the estimate drifts (flying) or holds (at rest on the ground: an
        estimator with zero-velocity updates, as PX4's EKF2 while landed, does not wander)."""
        last_t, last_tau, last_on = self._breaks[-1]
        if drifting == last_on or t < last_t:
            return
        self._breaks.append((t, last_tau + (t - last_t if last_on else 0.0), drifting))
        self._break_times.append(t)
        self._drift_cache = (None, None, None)

    def drift_time(self, t: float) -> float:
        """Seconds of drifting up to sim time t (the state after the last change lasts)."""
        i = max(0, bisect.bisect_right(self._break_times, t) - 1)
        bt, tau, on = self._breaks[i]
        return tau + (max(0.0, t - bt) if on else 0.0)

    def drifting(self, t: float) -> bool:
        return self._breaks[max(0, bisect.bisect_right(self._break_times, t) - 1)][2]

    def drift(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(rotation, translation) of the estimate's frame error at sim time t (memoised per t)."""
        if self._drift_cache[0] != t:
            tau = self.drift_time(t)
            self._drift_cache = (t, rot_z(self.drift_yaw_rate * tau), self.drift_vel * tau)
        return self._drift_cache[1], self._drift_cache[2]

    def estimate(self, t: float, pos_w, rot_w, vel_w) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free estimate (pos, rotation, velocity) in the local ENU reporting frame at time t."""
        rd, pd = self.drift(t)
        fr = self.frame_rot
        p_loc = fr.T @ (np.asarray(pos_w) - self.origin)
        bias = self.drift_vel if self.drifting(t) else 0.0
        return rd @ p_loc + pd, rd @ fr.T @ rot_w, rd @ fr.T @ np.asarray(vel_w) + bias

    def reframe(self, t: float, origin_world, frame_yaw: float, reset_counter: int) -> np.ndarray:
        """From sim time t on, report in a new frame (origin, yaw in the world), as an estimator that
        re-initialised (a reboot) or reset its position does; the drift carries on. Returns the 4x4
        carrying points of the old local estimate into the new one (for the flight controller)."""
        rd, pd = self.drift(t)
        old_rot, old_origin = self.frame_rot, self.origin
        self.origin = np.asarray(origin_world, float).copy()
        self.frame_yaw = float(frame_yaw)
        self.frame_rot = rot_z(frame_yaw)
        self.reset_counter = int(reset_counter)
        self.frame_log.append((t, self.origin.copy(), self.frame_yaw))
        # local = rd F^T (w - o) + pd  =>  local_new = R local_old + s
        rot = rd @ self.frame_rot.T @ old_rot @ rd.T
        out = np.eye(4)
        out[:3, :3] = rot
        out[:3, 3] = pd - rot @ pd + rd @ self.frame_rot.T @ (old_origin - self.origin)
        return out

    def frame_at(self, t: float) -> tuple[np.ndarray, float]:
        """(origin, frame yaw) of the reporting frame in use at sim time t."""
        origin, yaw = self.frame_log[0][1], self.frame_log[0][2]
        for t0, o, y in self.frame_log:
            if t0 <= t:
                origin, yaw = o, y
        return origin.copy(), yaw

    def local_to_world_vector(self, t: float, vec_local) -> np.ndarray:
        """Express a local-estimate-frame vector (e.g. a force) in the world frame."""
        rd, _ = self.drift(t)
        return self.frame_rot @ rd.T @ np.asarray(vec_local)

    def local_to_world_point(self, p_local) -> np.ndarray:
        """Map a point of the (drift-free) reporting frame into the world frame."""
        return self.frame_rot @ np.asarray(p_local) + self.origin

    def world_to_local_point(self, p_world) -> np.ndarray:
        """Map a world point into the (drift-free) reporting frame."""
        return self.frame_rot.T @ (np.asarray(p_world) - self.origin)

    def noisy(self, pos, rot, vel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add white noise (seeded) to an estimate before it is reported."""
        n = self.noise
        z = self._noise_rng.standard_normal(9)
        pos = pos + z[:3] * n.pos_sigma_m
        vel = vel + z[3:6] * n.vel_sigma_m_s
        if n.att_sigma_rad > 0:
            rot = _small_rotation(z[6:] * n.att_sigma_rad) @ rot
        return pos, rot, vel


def _small_rotation(a) -> np.ndarray:
    """Rotation matrix of a small rotation vector (Rodrigues)."""
    th = float(np.linalg.norm(a))
    if th < 1e-12:
        return np.eye(3)
    k = np.asarray(a) / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx


def world_to_lla(p_world) -> tuple[float, float, float]:
    """Flat-earth geodetic position (deg, deg, m AMSL) of a world ENU point."""
    lat0, lon0, alt0 = WORLD_ORIGIN_LLA
    lat = lat0 + math.degrees(p_world[1] / EARTH_RADIUS_M)
    lon = lon0 + math.degrees(p_world[0] / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return lat, lon, alt0 + float(p_world[2])


def lla_to_world(lat: float, lon: float, alt: float) -> np.ndarray:
    """World ENU point of a geodetic position (inverse of world_to_lla)."""
    lat0, lon0, alt0 = WORLD_ORIGIN_LLA
    north = math.radians(lat - lat0) * EARTH_RADIUS_M
    east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    return np.array([east, north, alt - alt0])
