"""Camera maths: the pose of a perturbed camera, and the kinematics that pose is computed from.

The Distracting Control Suite's camera perturbation (envs/distractions.py draws it) moves the
camera on a sphere: (radius, horizontal angle, vertical angle, roll), around the agent's centre of
mass for tracking cameras and around the world origin for fixed ones. The render workers
(envs/render.py) place the camera with `perturbed_camera_pose` after `kinematics` of the sample.
"""

import mujoco
import numpy as np


def kinematics(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """What drawing a state needs, and no more than mj_forward's position stage.

    Poses alone (mj_kinematics, mj_comPos, mj_camlight, mj_tendon) are not enough: MuJoCo draws a
    tendon at its limit in the constraint colour (ball_in_cup's taut string turns red), which
    needs the constraint rows of mj_fwdPosition. It costs 2-3 us per state on dm_control's
    models, nothing next to drawing.
    """
    mujoco.mj_fwdPosition(model, data)


def sphere_to_cart(sphere: np.ndarray) -> np.ndarray:
    """(radius, horizontal angle, vertical angle from +z) -> xyz."""
    r, h, v = sphere[0], sphere[1], sphere[2]
    return np.array([r * np.sin(v) * np.cos(h), r * np.sin(v) * np.sin(h), r * np.cos(v)])


def cart_to_sphere(xyz: np.ndarray) -> np.ndarray:
    r = float(np.linalg.norm(xyz))
    return np.array([r, np.arctan2(xyz[1], xyz[0]), np.arctan2(np.linalg.norm(xyz[:2]), xyz[2])])


def look_at_xmat(target: np.ndarray, position: np.ndarray, roll: float) -> np.ndarray:
    """Camera frame (MuJoCo: looks along -z, y up) at `position` facing `target`, level horizon,
    then rolled by `roll` about its viewing axis. Returns the 3x3 frame, columns = camera axes."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    norm = np.linalg.norm(right)
    # Looking straight up or down: any horizontal right axis keeps the view well defined.
    right = right / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    up = np.cross(right, forward)
    frame = np.stack([right, up, -forward], axis=1)
    c, s = np.cos(roll), np.sin(roll)
    roll_mat = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return frame @ roll_mat


def lookat_point(data: mujoco.MjData, cam_id: int, anchor: np.ndarray) -> np.ndarray:
    """The point on the camera's viewing axis as far away as `anchor` (the agent's centre)."""
    dist = np.linalg.norm(data.cam_xpos[cam_id] - anchor)
    return data.cam_xpos[cam_id] + data.cam_xmat[cam_id].reshape(3, 3) @ np.array([0, 0, -dist])


def perturbed_camera_pose(
    model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, sphere: np.ndarray, lookat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World position and frame of the perturbed camera for the current (kinematics-done) state."""
    tracking = model.cam_mode[cam_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED
    if tracking:
        com = data.subtree_com[1]
        position = sphere_to_cart(sphere) + com
        target = lookat_point(data, cam_id, com)
    else:
        position = sphere_to_cart(sphere)
        target = np.asarray(lookat, np.float64)
    return position, look_at_xmat(target, position, float(sphere[3]))


# ---------------------------------------------------------------------------------------------
