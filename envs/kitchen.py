"""Franka Kitchen (D4RL's scene): light switch and kettle, on MJX or CPU MuJoCo (docs/method.md).

This file owns everything task-specific about the kitchen: where the scene comes from, the
collision model MJX can step, the action -> actuator mapping, the episode start, the sparse
success reward, the reference camera and the robot's geoms for the agent mask.

Scene. `kitchen_env_model.xml` of the installed `gymnasium-robotics` package (its
`envs/assets/kitchen_franka` folder: the Franka arm, the kitchen and their meshes), found with
`importlib.util.find_spec` so the package itself (gymnasium, its env registry) is never imported,
and never copied into this repo. Qpos layout (30): 9 robot joints (7 arm hinges, 2 finger
slides), 8 burner knob/plate joints, light switch hinge (17) and light slide (18, tied to the
switch by an equality), slide cabinet, two hinge doors, microwave door (19-22), kettle free
joint (23-29, position then w-first quaternion).

Collision model (the physics model only; rendering draws the original model, its arm's meshes
simplified if `env.render.mesh_faces` asks: `build_render_model`). `mjx.put_model`
refuses the scene as shipped: the robot's collision meshes and the pedestal would collide with
cylinders (counter handles, oven knobs and bars, the kettle spout), and meshes cannot carry the
1 mm contact margin the kitchen geoms have. Every geom's contype/conaffinity is cleared and
contacts come back for four groups only, each a bit, all of them boxes:
- robot (bit 1): boxes fitted when the model is built to the shipped collision geometry: around
  the convex collision mesh of links 5, 6, 7 and of the hand (axis-aligned in the mesh's
  principal frame, where MuJoCo stores its vertices; tests check every vertex is inside), and
  per finger one box around its 13 pad primitives (12 capsules and a box), with the fingers'
  friction, solref, solimp and margin. Links 0-4 and the pedestal never come within 15 cm of
  the scene (20k joint configurations sampled uniformly in the joint ranges) and have no
  contacts; robot self-collisions are off.
- scene (bit 2): the kitchen's own collision boxes of the counters, the oven block (its top is
  the burner surface: the burner plates are visual only in the shipped scene too) and the hood
  under which the switch hangs, except the boxes farther than 1 m (the arm's reach) from the
  shoulder (four far walls of the sink); and the box around the switch lever's capsule.
  Cylinders (counter handles, faucet, knobs), the microwave, cabinets and walls have no
  contacts: neither task needs them, and each pair costs MJX time every physics step.
- kettle base (bit 4): the kettle's collision box; it rests on and slides over the scene.
- kettle grip (bit 8): boxes around the handle and posts (capsules) and the spout (cylinder);
  they touch the robot only.
Pairs: robot x {scene, kettle}, kettle base x scene: 100 box-box pairs. Why boxes only: MJX's
capsule-box routine missed 4 of 195 shallow contacts CPU MuJoCo finds (random poses of a finger-
sized capsule on a box, misses at the box's edges; a robot of capsules then slid past the lever
in MJX and not on the CPU), while box-box agreed on all 195 within 3.2 mm of depth (mean 0.45).
The fingers' condim is 3 instead of the shipped 6 (torsional and rolling friction): on a
scripted rollout (tests/test_kitchen.py) condim 6 left the switch at -0.13 rad on the CPU and
-0.43 in MJX and the arm pressed into the counter 1.2 rad apart; condim 3: -0.36 / -0.42 and
0.5 rad (the kettle keeps its condim 4). The added geoms have no mass, and the geoms without
contacts (231 of 252: visual meshes, cylinders, walls) are left out, every body keeping the
shipped mass and inertia as an explicit inertial (tests check the mass). A physics step computes
every geom's pose and bounding box, so without them an agent step of 48 envs takes ~30% less CPU
time, on the same states bit for bit (tested; benchmarks/RESULTS.md, "Franka Kitchen physics").
Both backends step this model; tests/test_kitchen.py states how closely they agree.

Actuation. The arm has position actuators (kp 870 / 120, fingers 500) and the action is a joint
velocity, as in D4RL and gymnasium-robotics: the 9-d action a in [-1, 1] is scaled by 2 (rad/s,
m/s), integrated over one agent step (40 physics steps of 2 ms = 0.08 s) from the current joint
positions, and clipped to the robot's position bounds (read from `franka_config.xml`); the
result is each actuator's target for the whole agent step (MuJoCo clips it to the ctrl range
too). D4RL integrates from its last *observed* joint positions, which carry a small uniform
noise; here the true positions are used, so stepping is deterministic. Velocity bounds (10) are
above 2 and never bind.

Episode start. D4RL's fixed initial state (its `init_qpos`: arm above the counter, kettle on
the bottom-left burner), zero velocities, no randomisation, as in D4RL and gymnasium-robotics.
Episodes last 280 agent steps (action repeat 1); reward 1 on the step the task's qpos slice gets
within 0.3 (Euclidean) of its goal, which ends the episode with discount 0 and success 1.

Camera. The reference's free camera (lookat (-0.3, 0.5, 2.0), distance 1.86, azimuth 90,
elevation -60, the model's 45 degree fovy) is added to the render model as a fixed camera at the
pose MuJoCo's free camera computes, so the render pool and the distraction code, which work on
model cameras, draw exactly the free camera's picture (tests compare the two).

Agent mask: the geoms of the robot's body tree, i.e. the pedestal, links 0-7, the hand and the
fingers; nothing of the kitchen, the kettle included. The reference renders segmentation at
252x252, cleans it with a morphological opening (which deletes specks and parts thinner than
its kernel) and resizes it to 84x84. Here the labels come from the same draw as the 84x84 RGB
observation (the render pool draws both per state, no multisampling), so the mask is exactly
the set of observation pixels that show the robot: no speck can arise that a cleaning step
would remove, and thin parts that are visible in the observation (finger tips) stay in the
mask. tests/test_kitchen.py checks mask == pixels whose segmentation geom is a robot body's.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import importlib.util
import os
import xml.etree.ElementTree as ET

import jax.numpy as jnp
import mujoco
import numpy as np

from envs.dmc import PhysicsView
from envs.render import simplify_meshes

SCENE_SUBDIR = os.path.join("envs", "assets", "kitchen_franka")
SCENE_XML = os.path.join("kitchen_assets", "kitchen_env_model.xml")
ROBOT_CONFIG_XML = os.path.join("franka_assets", "franka_config.xml")

CONTROL_TIMESTEP = 0.08  # 40 physics steps of 2 ms
EPISODE_STEPS = 280
SUCCESS_THRESHOLD = 0.3
ACTION_SCALE = 2.0  # action 1 = 2 rad/s (m/s for the fingers)
NUM_ROBOT_JOINTS = 9

# D4RL's initial state (kitchen_multitask_v0 `init_qpos`, also gymnasium-robotics').
INIT_QPOS = np.array(
    [
        1.48388023e-01, -1.76848573e00, 1.84390296e00, -2.47685760e00, 2.60252026e-01,
        7.12533105e-01, 1.59515394e00, 4.79267505e-02, 3.71350919e-02, -2.66279850e-04,
        -5.18043486e-05, 3.12877220e-05, -4.51199853e-05, -3.90842156e-06, -4.22629655e-05,
        6.28065475e-05, 4.04984708e-05, 4.62730939e-04, -2.26906415e-04, -4.65501369e-04,
        -6.44129196e-03, -1.77048263e-03, 1.08009684e-03, -2.69397440e-01, 3.50383255e-01,
        1.61944683e00, 1.00618764e00, 4.06395120e-03, -6.62095997e-03, -2.68278933e-04,
    ]
)  # fmt: skip

CAMERA_NAME = "reference"
CAMERA_LOOKAT = (-0.3, 0.5, 2.0)
CAMERA_DISTANCE = 1.86
CAMERA_AZIMUTH = 90.0  # degrees
CAMERA_ELEVATION = -60.0  # degrees

# Contact groups: (contype, conaffinity). A pair collides when contype of one matches the
# conaffinity of the other: robot-scene, robot-kettle (base and grip), kettle base-scene.
ROBOT, SCENE, KETTLE_BASE, KETTLE_GRIP = 1, 2, 4, 8
CONTACT_BITS = {
    "robot": (ROBOT, SCENE | KETTLE_BASE | KETTLE_GRIP),
    "scene": (SCENE, ROBOT | KETTLE_BASE),
    "kettle_base": (KETTLE_BASE, ROBOT | SCENE),
    "kettle_grip": (KETTLE_GRIP, ROBOT),
}
SCENE_BOX_BODIES = ("counters", "ovenroot", "hoodroot")  # their collision boxes
SWITCH_BODY = "lightswitchroot"  # its collision capsule, as a box
KETTLE_BODY = "kettleroot"
BOX_LINKS = ("panda0_link5", "panda0_link6", "panda0_link7")
SHOULDER_BODY = "panda0_link2"  # its origin (on joints 1 and 2) does not move
REACH = 1.0  # m from the shoulder: links 0.316 + 0.384 + 0.088, flange and hand 0.107, fingers
HAND_MESH = "hand_col"
FINGER_BODIES = ("panda0_leftfinger", "panda0_rightfinger")
FINGER_CONDIM = 3  # shipped: 6, on which MJX and MuJoCo disagree (module docstring)
ROBOT_ROOT_CHILD = "panda0_link0"  # the pedestal is its parent (an unnamed body)

# Plain ints: numpy ints and MuJoCo's enums do not compare equal in every direction.
_BOX, _CAPSULE = int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_CYLINDER, _MESH = int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_MESH)


# --------------------------------------------------------------------------------------------
# The scene files.


@functools.lru_cache(maxsize=1)
def scene_dir() -> str:
    """`envs/assets/kitchen_franka` of the installed gymnasium-robotics (not imported)."""
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            "gymnasium-robotics is not installed; the kitchen tasks load D4RL's kitchen scene "
            "from it (pip install gymnasium-robotics==1.4.2)"
        )
    for root in spec.submodule_search_locations:
        path = os.path.join(root, SCENE_SUBDIR)
        if os.path.isfile(os.path.join(path, SCENE_XML)):
            return path
    raise FileNotFoundError(
        f"no {SCENE_SUBDIR}/{SCENE_XML} in gymnasium_robotics at {spec.submodule_search_locations}"
    )


def load_spec() -> mujoco.MjSpec:
    return mujoco.MjSpec.from_file(os.path.join(scene_dir(), SCENE_XML))


@functools.lru_cache(maxsize=1)
def robot_position_bounds() -> tuple[np.ndarray, np.ndarray]:
    """(low, high) [9] joint position bounds of franka_config.xml's qpos0..qpos8 entries."""
    root = ET.parse(os.path.join(scene_dir(), ROBOT_CONFIG_XML)).getroot()
    bounds = []
    for i in range(NUM_ROBOT_JOINTS):
        node = root.find(f"qpos{i}")
        if node is None:
            raise ValueError(f"{ROBOT_CONFIG_XML} has no qpos{i} entry")
        bounds.append([float(x) for x in node.get("pos_bound").split()])
    low, high = np.array(bounds).T
    return low, high


# --------------------------------------------------------------------------------------------
# Fitting primitives to the shipped collision geometry (all in the compiled original model).


def _quat_mat(quat) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def _mat_quat(mat: np.ndarray) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.asarray(mat, np.float64).reshape(-1))
    return quat


def mesh_vertices(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """Vertices [n, 3] of a mesh geom in the geom's frame (MuJoCo centres meshes there)."""
    mesh = model.geom_dataid[geom]
    start = model.mesh_vertadr[mesh]
    return model.mesh_vert[start : start + model.mesh_vertnum[mesh]].astype(np.float64)


def primitive_half_extents(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """Half extents [3] of the box around a box, capsule or cylinder geom, in its own frame."""
    size, kind = model.geom_size[geom], int(model.geom_type[geom])
    if kind == _BOX:
        return size.copy()
    if kind == _CAPSULE:
        return np.array([size[0], size[0], size[1] + size[0]])
    if kind == _CYLINDER:
        return np.array([size[0], size[0], size[1]])
    raise ValueError(f"geom {geom}: no box for type {mujoco.mjtGeom(kind)}")


def _box_corners(pos, rot, half) -> np.ndarray:
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    return pos + (signs * half) @ rot.T


def _box_distance(data: mujoco.MjData, model: mujoco.MjModel, geom: int, point) -> float:
    """Distance from a world point to a box geom (0 inside)."""
    local = data.geom_xmat[geom].reshape(3, 3).T @ (point - data.geom_xpos[geom])
    half = model.geom_size[geom]
    return float(np.linalg.norm(local - np.clip(local, -half, half)))


def _collides(model: mujoco.MjModel, geom: int) -> bool:
    return bool(model.geom_contype[geom] or model.geom_conaffinity[geom])


def _contact_params(model: mujoco.MjModel, geom: int) -> dict:
    """Contact parameters of a compiled geom, as MjSpec geom attributes."""
    return dict(
        condim=int(model.geom_condim[geom]),
        friction=model.geom_friction[geom].copy(),
        solref=model.geom_solref[geom].copy(),
        solimp=model.geom_solimp[geom].copy(),
        margin=float(model.geom_margin[geom]),
    )


def _add_box(body: mujoco.MjsBody, group: str, params: dict, pos, quat, half) -> None:
    contype, conaffinity = CONTACT_BITS[group]
    body.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=pos,
        quat=quat,
        size=half,
        contype=contype,
        conaffinity=conaffinity,
        group=3,  # hidden, like the shipped collision geoms
        mass=0.0,  # the bodies keep the shipped mass and inertia
        rgba=[0.9, 0.4, 0.2, 0.5],
        **params,
    )


def build_physics_model() -> mujoco.MjModel:
    """The shipped scene with the collision model described in the module docstring."""
    return _without_contactless_geoms(*collision_spec())


def collision_spec() -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    """The shipped scene's spec with the collision model (every geom kept), and the shipped
    scene compiled."""
    spec = load_spec()
    orig = spec.compile()
    geoms = list(spec.geoms)  # the compiled order; new geoms join their bodies' lists below
    for g in geoms:
        g.contype, g.conaffinity = 0, 0

    body_of = [orig.body(orig.geom_bodyid[i]).name for i in range(orig.ngeom)]
    data = mujoco.MjData(orig)
    mujoco.mj_kinematics(orig, data)
    shoulder = data.xpos[orig.body(SHOULDER_BODY).id]
    for i in range(orig.ngeom):
        if not _collides(orig, i):
            continue
        kind, body, params = int(orig.geom_type[i]), body_of[i], _contact_params(orig, i)
        pos, quat = orig.geom_pos[i], orig.geom_quat[i]
        if body in SCENE_BOX_BODIES and kind == _BOX:
            if _box_distance(data, orig, i, shoulder) < REACH:
                geoms[i].contype, geoms[i].conaffinity = CONTACT_BITS["scene"]
        elif body == SWITCH_BODY:
            _add_box(spec.body(body), "scene", params, pos, quat, primitive_half_extents(orig, i))
        elif body == KETTLE_BODY:
            group = "kettle_base" if kind == _BOX else "kettle_grip"
            _add_box(spec.body(body), group, params, pos, quat, primitive_half_extents(orig, i))
        elif kind == _MESH and (
            body in BOX_LINKS or orig.mesh(orig.geom_dataid[i]).name == HAND_MESH
        ):
            verts = mesh_vertices(orig, i)  # in the mesh's principal frame
            lo, hi = verts.min(0), verts.max(0)
            centre = pos + _quat_mat(quat) @ ((lo + hi) / 2)
            _add_box(spec.body(body), "robot", params, centre, quat, (hi - lo) / 2)

    for body in FINGER_BODIES:
        pads = [i for i in range(orig.ngeom) if body_of[i] == body and _collides(orig, i)]
        corners = np.concatenate(
            [
                _box_corners(
                    orig.geom_pos[i], _quat_mat(orig.geom_quat[i]), primitive_half_extents(orig, i)
                )
                for i in pads
            ]
        )
        lo, hi = corners.min(0), corners.max(0)
        params = _contact_params(orig, pads[0]) | {"condim": FINGER_CONDIM}
        _add_box(spec.body(body), "robot", params, (lo + hi) / 2, [1.0, 0, 0, 0], (hi - lo) / 2)
    return spec, orig


def _without_contactless_geoms(spec: mujoco.MjSpec, shipped: mujoco.MjModel) -> mujoco.MjModel:
    """`spec` compiled without its geoms that take part in no contact, each body keeping the
    mass, centre of mass and inertia `shipped` (the same bodies, in the same order) gives it."""
    bodies = list(spec.bodies)
    names = [b.name for b in bodies]
    if len(bodies) != shipped.nbody or any(
        name and name != shipped.body(i).name for i, name in enumerate(names)
    ):
        raise ValueError("the spec's bodies are not the compiled model's, in its order")
    for i, body in enumerate(bodies[1:], start=1):  # the world has no inertial
        body.explicitinertial = True
        body.mass = shipped.body_mass[i]
        body.ipos = shipped.body_ipos[i]
        body.iquat = shipped.body_iquat[i]
        body.inertia = shipped.body_inertia[i]  # principal moments, in the iquat frame
        body.fullinertia = [np.nan, 0, 0, 0, 0, 0]  # unset (MuJoCo's marker): not a full one
    for geom in list(spec.geoms):
        if geom.contype == 0 and geom.conaffinity == 0:
            spec.delete(geom)
    return spec.compile()


def build_render_model(mesh_faces: int = 0) -> mujoco.MjModel:
    """The shipped scene (original visuals) plus the reference camera as a fixed camera.

    mesh_faces > 0: meshes of more faces drawn simplified to about that many
    (`envs.render.simplify_meshes`): the arm's nine visual meshes hold 134k of the scene's 142k
    faces, which a Hopper GPU's few raster units draw slowly (benchmarks/RESULTS.md, "Franka
    Kitchen rendering"); at 4,000 the 84x84 frames differ from the shipped meshes' by 0.5-0.7 of
    255 levels per pixel (docs/method.md, decision 16; tests/test_kitchen.py)."""
    spec = load_spec()
    simplify_meshes(
        spec, mesh_faces, os.path.join(scene_dir(), os.path.dirname(SCENE_XML), spec.meshdir)
    )
    pos, quat = free_camera_pose(CAMERA_LOOKAT, CAMERA_DISTANCE, CAMERA_AZIMUTH, CAMERA_ELEVATION)
    fovy = spec.visual.global_.fovy
    spec.worldbody.add_camera(name=CAMERA_NAME, pos=pos, quat=quat, fovy=fovy)
    model = spec.compile()
    # The scene asks for a 2560x1920 offscreen buffer (slow on software GL, where every frame
    # pays for the whole buffer); MuJoCo's default, as the DMC models have, and the render pool
    # enlarges it when its tile sheets need more.
    model.vis.global_.offwidth, model.vis.global_.offheight = 640, 480
    return model


def free_camera_pose(lookat, distance, azimuth, elevation) -> tuple[np.ndarray, np.ndarray]:
    """Position and w-first quaternion of MuJoCo's free camera (mjv_updateCamera's formulas)."""
    az, el = np.deg2rad(azimuth), np.deg2rad(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    right = np.cross(forward, up)
    # MuJoCo cameras look along their -z axis with +y up.
    frame = np.stack([right, up, -forward], axis=1)
    return np.asarray(lookat, np.float64) - distance * forward, _mat_quat(frame)


@functools.lru_cache(maxsize=1)
def _physics_model_cached() -> mujoco.MjModel:
    return build_physics_model()


@functools.lru_cache(maxsize=2)
def _render_model_cached(mesh_faces: int) -> mujoco.MjModel:
    return build_render_model(mesh_faces)


def robot_body_ids(model: mujoco.MjModel) -> tuple[int, ...]:
    """The pedestal body and every body below it (the links, hand and fingers)."""
    root = model.body_parentid[model.body(ROBOT_ROOT_CHILD).id]
    ids = []
    for b in range(model.nbody):
        a = b
        while a != 0 and a != root:
            a = model.body_parentid[a]
        if a == root:
            ids.append(b)
    return tuple(ids)


# --------------------------------------------------------------------------------------------
# Control, reward, task table.


@dataclasses.dataclass(frozen=True)
class JointVelocityControl:
    """action [9] in [-1, 1] -> position actuator targets: q + scale * dt * a, clipped."""

    step: float  # ACTION_SCALE * CONTROL_TIMESTEP
    low: np.ndarray  # [9]
    high: np.ndarray  # [9]

    def __call__(self, qpos, action, xp=jnp):
        """xp: jax.numpy (MJX, traced) or numpy (CPU MuJoCo). qpos [nq], action [9]."""
        action = xp.clip(action, -1.0, 1.0)
        target = qpos[:NUM_ROBOT_JOINTS] + self.step * action
        return xp.clip(target, self.low, self.high)


@dataclasses.dataclass(frozen=True)
class KitchenTask:
    """One kitchen task: the object's qpos slice and its goal; the rest is shared."""

    name: str  # registry name
    object_qpos: tuple[int, ...]  # qpos indices of the object
    goal: tuple[float, ...]  # their goal values
    camera: str = CAMERA_NAME
    floor_geoms: tuple[str, ...] = ("floor",)
    floor_alpha: float = 1.0  # the floor is hidden under the kitchen from this camera
    success_ends_episode: bool = True

    def physics_model(self) -> mujoco.MjModel:
        return copy.copy(_physics_model_cached())

    def render_model(self, mesh_faces: int = 0) -> mujoco.MjModel:
        """The model the render workers draw; mesh_faces: `build_render_model`'s."""
        return copy.copy(_render_model_cached(mesh_faces))

    def render_factory(self, mesh_faces: int = 0):
        """Picklable zero-argument model factory for the render workers."""
        return functools.partial(render_model_fn, self.name, mesh_faces)

    def n_sub_steps(self, model: mujoco.MjModel) -> int:
        n = CONTROL_TIMESTEP / model.opt.timestep
        if abs(n - round(n)) > 1e-6:
            raise ValueError(f"{self.name}: control timestep is not a multiple of the timestep")
        return int(round(n))

    def frames_per_episode(self, model: mujoco.MjModel) -> int:
        return EPISODE_STEPS

    def make_reward(self, model: mujoco.MjModel):
        idx = np.asarray(self.object_qpos)
        goal = np.asarray(self.goal, np.float32)

        def reward(v: PhysicsView):
            distance = jnp.linalg.norm(v.qpos[idx] - goal)
            return (distance < SUCCESS_THRESHOLD).astype(jnp.float32)

        return reward

    def make_control(self, model: mujoco.MjModel) -> JointVelocityControl:
        low, high = robot_position_bounds()
        return JointVelocityControl(step=ACTION_SCALE * CONTROL_TIMESTEP, low=low, high=high)

    def init_episode(self, model, data, rng: np.random.RandomState) -> None:
        del rng  # D4RL's start is fixed
        data.qpos[:] = INIT_QPOS
        data.qvel[:] = 0.0

    def goal_distance(self, qpos: np.ndarray) -> np.ndarray:
        """Host helper: distance of the object to its goal. qpos [..., nq] -> [...]."""
        qpos = np.asarray(qpos)
        return np.linalg.norm(qpos[..., list(self.object_qpos)] - np.asarray(self.goal), axis=-1)

    def agent_geom_ids(self, model: mujoco.MjModel) -> tuple[int, ...]:
        bodies = set(robot_body_ids(model))
        return tuple(g for g in range(model.ngeom) if model.geom_bodyid[g] in bodies)

    def floor_geom_ids(self, model: mujoco.MjModel) -> tuple[int, ...]:
        return tuple(model.geom(name).id for name in self.floor_geoms)


def render_model_fn(task_name: str, mesh_faces: int = 0) -> mujoco.MjModel:
    """Model factory for render workers: `functools.partial(render_model_fn, name, faces)`."""
    return TASKS[task_name].render_model(mesh_faces)


TASKS: dict[str, KitchenTask] = {
    t.name: t
    for t in [
        KitchenTask(name="kitchen-light", object_qpos=(17, 18), goal=(-0.69, -0.05)),
        KitchenTask(
            name="kitchen-kettle",
            object_qpos=(23, 24, 25, 26, 27, 28, 29),
            goal=(-0.23, 0.75, 1.62, 0.99, 0.0, 0.0, -0.06),
        ),
    ]
}
