"""Helpers for tests against firmware_sim: waiting, truth in a vehicle's map frame."""

import time

import numpy as np

from coopd.geometry import quat_to_matrix, rotation_angle_deg
from coopd.vehicle.pose_buffer import PoseBuffer, PoseSample


def wait_until(predicate, timeout: float, poll: float = 0.02) -> bool:
    """Poll predicate until true or timeout (seconds); returns its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return bool(predicate())


def truth_buffer(sim, i: int = 0) -> PoseBuffer:
    """The emulator's logged true trajectory (world frame) as an interpolable buffer."""
    rows = sim.trajectory(i)
    buf = PoseBuffer(capacity=len(rows) + 2, max_gap_s=0.1)
    for r in rows:
        buf.append(PoseSample(float(r[0]), r[1:4].copy(), r[4:8].copy()))
    return buf


def pose_errors(link, sim, i: int = 0):
    """(position error m, attitude error deg) of every buffered map-frame pose vs the truth
    expressed in the vehicle's odometry frame and shifted to the link's map origin."""
    truth = truth_buffer(sim, i)
    odo = sim.vehicle(i).odometry
    span = truth.span()
    pos_err, att_err = [], []
    for s in link.poses.samples():
        if not span[0] <= s.t_fc <= span[1]:
            continue
        t = truth.at(s.t_fc)
        expected = odo.world_to_local_point(t.position) - link.odometry.origin_enu
        pos_err.append(float(np.linalg.norm(s.position - expected)))
        r_expected = odo.frame_rot.T @ quat_to_matrix(t.quaternion)
        att_err.append(rotation_angle_deg(quat_to_matrix(s.quaternion).T @ r_expected))
    return np.array(pos_err), np.array(att_err)
