"""Cascaded quadrotor controller (position -> velocity -> thrust vector -> attitude -> torque), pure."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GRAVITY = 9.81


@dataclass(frozen=True)
class Airframe:
    """Physical constants of the simulated quadrotor (PX4 x500-like, about 1.5 kg)."""

    mass: float = 1.5
    inertia: tuple[float, float, float] = (0.029, 0.029, 0.055)
    max_thrust_to_weight: float = 2.0
    max_torque: tuple[float, float, float] = (1.5, 1.5, 0.3)
    linear_drag: float = 0.35  # N per m/s, applied by the physics, unknown to the controller
    half_extent: tuple[float, float, float] = (0.22, 0.22, 0.05)


@dataclass(frozen=True)
class Gains:
    """Controller gains and limits (PX4 MPC_* analogues)."""

    pos_p: float = 1.0
    vel_p: float = 3.0
    vel_i: float = 0.4
    max_speed_xy: float = 2.0
    max_speed_z_up: float = 1.0
    max_speed_z_down: float = 0.8
    max_accel_xy: float = 3.0
    max_tilt: float = math.radians(30)
    att_p: float = 8.0
    att_d: float = 1.0
    yaw_p: float = 3.0
    max_yaw_rate: float = math.radians(90)


def velocity_setpoint(pos, pos_sp, gains: Gains, max_speed_xy: float | None = None) -> np.ndarray:
    """Position P-loop: velocity towards the setpoint, saturated with the direction kept."""
    v = gains.pos_p * (np.asarray(pos_sp) - np.asarray(pos))
    vmax = gains.max_speed_xy if max_speed_xy is None else max_speed_xy
    h = math.hypot(v[0], v[1])
    if h > vmax:
        v[:2] *= vmax / h
    v[2] = min(max(v[2], -gains.max_speed_z_down), gains.max_speed_z_up)
    return v


def thrust_vector(vel, vel_sp, vel_integral, airframe: Airframe, gains: Gains) -> np.ndarray:
    """Velocity PI-loop: the desired force (N, local ENU) including gravity, tilt and thrust limited."""
    acc = gains.vel_p * (np.asarray(vel_sp) - np.asarray(vel)) + gains.vel_i * np.asarray(vel_integral)
    h = math.hypot(acc[0], acc[1])
    if h > gains.max_accel_xy:
        acc[:2] *= gains.max_accel_xy / h
    fz = airframe.mass * (GRAVITY + acc[2])
    fz = min(max(fz, 0.2 * airframe.mass * GRAVITY), airframe.max_thrust_to_weight * airframe.mass * GRAVITY)
    fxy = airframe.mass * acc[:2]
    max_xy = fz * math.tan(gains.max_tilt)
    n = math.hypot(fxy[0], fxy[1])
    if n > max_xy:
        fxy *= max_xy / n
    return np.array([fxy[0], fxy[1], fz])


def _cross(a, b) -> tuple[float, float, float]:
    """Cross product of two 3-vectors as plain floats (np.cross is slow for single vectors)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def desired_rotation(force, yaw: float) -> np.ndarray:
    """Rotation (body FLU in ENU) whose z axis is along the force and whose heading is yaw."""
    fx, fy, fz = (float(v) for v in force)
    n = max(1e-9, math.sqrt(fx * fx + fy * fy + fz * fz))
    z = (fx / n, fy / n, fz / n)
    y = _cross(z, (math.cos(yaw), math.sin(yaw), 0.0))
    ny = max(1e-9, math.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2))
    y = (y[0] / ny, y[1] / ny, y[2] / ny)
    x = _cross(y, z)
    return np.array([[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]])


def attitude_torque(r, r_des, omega_body, airframe: Airframe, gains: Gains) -> np.ndarray:
    """Geometric attitude PD-loop on SO(3): body torque (N m), saturated per axis."""
    e = 0.5 * (r_des.T @ r - r.T @ r_des)
    e_r = np.array([e[2, 1], e[0, 2], e[1, 0]])
    inertia = np.asarray(airframe.inertia)
    wn2 = np.array([gains.att_p**2, gains.att_p**2, gains.yaw_p**2])
    damp = np.array([2 * 0.9 * gains.att_p, 2 * 0.9 * gains.att_p, 2 * 1.0 * gains.yaw_p])
    tau = -inertia * (wn2 * e_r + damp * np.asarray(omega_body))
    return np.clip(tau, -np.asarray(airframe.max_torque), np.asarray(airframe.max_torque))


def collective_thrust(force, r) -> float:
    """Thrust magnitude along the current body z axis that realises the force's vertical intent."""
    return max(0.0, float(np.dot(force, r[:, 2])))


def slew_yaw(current: float, target: float, max_rate: float, dt: float) -> float:
    """Move a yaw setpoint towards target by at most max_rate * dt, taking the short way round."""
    d = (target - current + math.pi) % (2 * math.pi) - math.pi
    step = max(-max_rate * dt, min(max_rate * dt, d))
    return (current + step + math.pi) % (2 * math.pi) - math.pi
