"""DeepMind Control Suite tasks: models, initial states, JAX rewards and render facts.

This file owns everything task-specific about the DMC tasks: which XML of the installed
`dm_control` package a task loads (found with `importlib.util.find_spec`, so dm_control's own
heavy imports are never needed at run time, and its XMLs are never copied into this repo), the
model edits a task makes, the episode-start randomisation (host side, CPU MuJoCo, the same rules
as dm_control's `initialize_episode`), the reward as a pure `jnp` function of a `PhysicsView`
(equal to dm_control's `get_reward`; `tests/test_envs.py` checks this against dm_control itself),
and the render facts: camera, floor geoms, floor alpha and the agent geoms.

Agent geoms (docs/method.md, Masks). The rule is "the geoms of the bodies the agent actuates":
- walker, cheetah: every geom of the body tree under `torso` (all geoms but the floor).
- ball_in_cup: the cup's five capsules and the ball (the reference counts the ball).
- finger: the geoms of the `proximal` and `distal` bodies (including the decoration cylinder at
  the finger's base), not the spinner's.
- cartpole: the cart and the pole (the rails are scenery).
Tendons and sites are not geoms and never count as agent: the cup's string (a 3 mm wide tendon,
well under a pixel at 84x84) and any visible site are labelled "other" by the render pool. Finger
spin hides its `target` and `tip` sites (alpha 0, as dm_control's Spin task does) and the touch
sites are in a hidden group, so no finger site is ever drawn.

Episode starts (`episode_start`) run on the host with CPU MuJoCo because two tasks reject states
in contact (ball_in_cup, finger: `ncon > 0`) and cheetah settles for 200 physics steps; both are
cheap on the CPU. They draw dm_control's numbers in dm_control's order, so one seed gives
dm_control's starts (tests/test_starts.py). The CPU backend starts from the resulting qpos/qvel;
the MJX backend uploads them.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import os
from collections.abc import Callable

import flax.struct
import jax.numpy as jnp
import mujoco
import numpy as np

# --------------------------------------------------------------------------------------------
# The physics state a reward reads (one environment; the backends vmap over (S, E)).


@flax.struct.dataclass
class PhysicsView:
    """Position- and velocity-stage quantities after a control step (dm_control's
    `mj_step1`-synchronised data). Shapes are for one environment."""

    qpos: jnp.ndarray  # [nq]
    qvel: jnp.ndarray  # [nv]
    ctrl: jnp.ndarray  # [nu]
    xpos: jnp.ndarray  # [nbody, 3]
    xmat: jnp.ndarray  # [nbody, 3, 3]
    site_xpos: jnp.ndarray  # [nsite, 3]
    sensordata: jnp.ndarray  # [nsensordata]


def _view_fields(data: mujoco.MjData) -> dict[str, np.ndarray]:
    """The fields a reward reads, as arrays onto `data` (not copies)."""
    return dict(
        qpos=data.qpos,
        qvel=data.qvel,
        ctrl=data.ctrl,
        xpos=data.xpos,
        xmat=data.xmat.reshape(-1, 3, 3),
        site_xpos=data.site_xpos,
        sensordata=data.sensordata,
    )


def view_from_mjdata(data: mujoco.MjData) -> PhysicsView:
    """Host copy of the fields a reward reads (numpy leaves)."""
    return PhysicsView(**{k: v.copy() for k, v in _view_fields(data).items()})


def write_view(out: PhysicsView, index, data: mujoco.MjData) -> None:
    """view_from_mjdata(data) written into the batched host view `out` at `index`."""
    for k, v in _view_fields(data).items():
        getattr(out, k)[index] = v


# --------------------------------------------------------------------------------------------
# dm_control's `rewards.tolerance`, in jnp.


def _sigmoid(x, value_at_margin, kind):
    if kind == "gaussian":
        scale = np.sqrt(-2 * np.log(value_at_margin))
        return jnp.exp(-0.5 * (x * scale) ** 2)
    if kind == "linear":
        scaled = x * (1 - value_at_margin)
        return jnp.where(jnp.abs(scaled) < 1, 1 - scaled, 0.0)
    if kind == "quadratic":
        scaled = x * np.sqrt(1 - value_at_margin)
        return jnp.where(jnp.abs(scaled) < 1, 1 - scaled**2, 0.0)
    raise ValueError(f"unknown sigmoid {kind!r}; valid: gaussian, linear, quadratic")


def tolerance(x, bounds=(0.0, 0.0), margin=0.0, sigmoid="gaussian", value_at_margin=0.1):
    """1 inside `bounds`, decaying by `sigmoid` to `value_at_margin` at distance `margin`."""
    lower, upper = bounds
    in_bounds = (lower <= x) & (x <= upper)
    if margin == 0:
        return jnp.where(in_bounds, 1.0, 0.0)
    # The branch not taken may hold inf (one-sided bounds); `where` discards it.
    distance = jnp.where(x < lower, lower - x, x - upper) / margin
    return jnp.where(in_bounds, 1.0, _sigmoid(distance, value_at_margin, sigmoid))


# --------------------------------------------------------------------------------------------
# Model loading.


@functools.lru_cache(maxsize=1)
def suite_dir() -> str:
    """The `suite` folder of the installed dm_control package (its XMLs and common assets)."""
    spec = importlib.util.find_spec("dm_control")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            "dm_control is not installed; the DMC tasks load their XML models from it "
            "(pip install dm-control==1.0.50)"
        )
    for root in spec.submodule_search_locations:
        path = os.path.join(root, "suite")
        if os.path.isdir(path):
            return path
    raise FileNotFoundError(f"no suite/ folder in dm_control at {spec.submodule_search_locations}")


def load_model(xml_file: str) -> mujoco.MjModel:
    """Compile a suite XML; its `./common/*.xml` includes resolve next to the file."""
    return mujoco.MjModel.from_xml_path(os.path.join(suite_dir(), xml_file))


# --------------------------------------------------------------------------------------------
# Episode starts: dm_control's `control.Environment.reset`, each task's `initialize_episode` and
# `suite/utils/randomizers.py`, drawn from a numpy RandomState in dm_control's order, so that one
# seed gives the starts dm_control gives.

# Plain ints: a numpy integer from `jnt_type` never equals a pybind enum member on the enum's
# side, so `jnt_type[j] in (mjJNT_HINGE, ...)` is always false.
_FREE, _BALL, _SLIDE, _HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)


def _axis_angle_quat(axis: np.ndarray, angle: float) -> np.ndarray:
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def _randomize_limited_and_rotational_joints(model, data, rng: np.random.RandomState) -> None:
    """dm_control's `randomizers.randomize_limited_and_rotational_joints`, joint by joint:
    limited hinge/slide: uniform over the range; unlimited hinge: uniform over [-pi, pi];
    limited ball: a uniform axis turned by an angle uniform over [0, range max]
    (`random_limited_quaternion`); unlimited ball: uniform on the unit 3-sphere; free: only the
    quaternion, drawn with `rand` (the positive orthant; dm_control keeps this on purpose, its
    comment says, for benchmark continuity). Unlimited slides and free positions keep their
    value."""
    for j in range(model.njnt):
        kind = int(model.jnt_type[j])
        adr = model.jnt_qposadr[j]
        lo, hi = model.jnt_range[j]
        if model.jnt_limited[j]:
            if kind in (_HINGE, _SLIDE):
                data.qpos[adr] = rng.uniform(lo, hi)
            elif kind == _BALL:
                axis = rng.randn(3)
                axis /= np.linalg.norm(axis)
                data.qpos[adr : adr + 4] = _axis_angle_quat(axis, rng.rand() * hi)
        elif kind == _HINGE:
            data.qpos[adr] = rng.uniform(-np.pi, np.pi)
        elif kind == _BALL:
            quat = rng.randn(4)
            data.qpos[adr : adr + 4] = quat / np.linalg.norm(quat)
        elif kind == _FREE:
            quat = rng.rand(4)
            data.qpos[adr + 3 : adr + 7] = quat / np.linalg.norm(quat)


def _legacy_steps(model, data, nstep: int) -> None:
    """dm_control's `Physics.step(nstep)` with legacy stepping: `mj_step2` finishes a step
    whose position stage is whatever the data holds (not recomputed for a qpos written since),
    then `mj_step` x (nstep - 1) and `mj_step1`; RK4 takes `mj_step` x nstep, then `mj_step1`."""
    if model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
        mujoco.mj_step(model, data, nstep)
    else:
        mujoco.mj_step2(model, data)
        if nstep > 1:
            mujoco.mj_step(model, data, nstep - 1)
    mujoco.mj_step1(model, data)


def _init_walker(model, data, rng):
    # Walker's `PlanarWalker.initialize_episode`: every joint by the randomizer (rooty over
    # [-pi, pi], the six leg hinges over their ranges; rootx and rootz are unlimited slides and
    # stay at 0). No rejection: a start may touch the floor.
    _randomize_limited_and_rotational_joints(model, data, rng)


# cheetah's `Cheetah.initialize_episode` lets the model fall for this many physics steps.
CHEETAH_SETTLE_STEPS = 200


def _init_cheetah(model, data, rng):
    # `Cheetah.initialize_episode`: the limited joints (the six leg hinges; the root joints are
    # unlimited) uniform over their ranges in one vectorised draw, then 200 physics steps of
    # settling starting from the position stage of the reset pose, then the clock back to 0.
    # qpos is indexed by joint, which needs one qpos entry per joint (dm_control asserts it).
    if model.nq != model.njnt:
        raise ValueError(f"cheetah: {model.nq} qpos entries for {model.njnt} joints")
    limited = model.jnt_limited == 1
    lower, upper = model.jnt_range[limited].T
    data.qpos[limited] = rng.uniform(lower, upper)
    if CHEETAH_SETTLE_STEPS:
        _legacy_steps(model, data, CHEETAH_SETTLE_STEPS)
    data.time = 0.0


def _init_ball_in_cup(model, data, rng):
    # `BallInCup.initialize_episode`: ball x over [-0.2, 0.2], then z over [0.2, 0.5], redrawn
    # (no attempt limit) until the forward pass finds no contact; the cup stays at 0.
    x, z = model.joint("ball_x").qposadr[0], model.joint("ball_z").qposadr[0]
    while True:
        data.qpos[x] = rng.uniform(-0.2, 0.2)
        data.qpos[z] = rng.uniform(0.2, 0.5)
        mujoco.mj_forward(model, data)
        if data.ncon == 0:
            return


def _init_finger(model, data, rng, max_attempts: int = 1000):
    # finger's `_set_random_joint_angles` (called by `Spin.initialize_episode`): all three
    # joints by the randomizer (proximal and distal over their ranges, the spinner's unlimited
    # `hinge` over [-pi, pi]), redrawn together until no contact, at most 1000 attempts. Spin
    # moves no target; its hinge damping and hidden sites are model edits (_finger_spin_*).
    for _ in range(max_attempts):
        _randomize_limited_and_rotational_joints(model, data, rng)
        mujoco.mj_forward(model, data)
        if data.ncon == 0:
            return
    raise RuntimeError(f"finger: no collision-free state after {max_attempts} attempts")


def _init_cartpole_swingup(model, data, rng):
    # `Balance.initialize_episode` with swing_up: slider 0.01 N(0,1), pole pi + 0.01 N(0,1), any
    # further poles 0.1 N(0,1), then every qvel 0.01 N(0,1), drawn in that order.
    slider, hinge = model.joint("slider").qposadr[0], model.joint("hinge_1").qposadr[0]
    data.qpos[slider] = 0.01 * rng.randn()
    data.qpos[hinge] = np.pi + 0.01 * rng.randn()
    data.qpos[2:] = 0.1 * rng.randn(model.nv - 2)
    data.qvel[:] = 0.01 * rng.randn(model.nv)


def episode_start(task: DmcTask, model, data, rng: np.random.RandomState) -> None:
    """Draw one episode start into `data`, as dm_control's `control.Environment.reset` does:
    `Physics.reset` (`mj_resetData`, then a forward pass), the task's `initialize_episode`, then
    `Physics.after_reset` (a forward pass). dm_control runs both forward passes with actuation
    disabled; that changes only actuator outputs, never qpos, qvel or contacts, and cheetah's
    first settling `mj_step2` recomputes actuation itself, so they run plainly here."""
    mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)
    task.init_episode(model, data, rng)
    mujoco.mj_forward(model, data)


def episode_starts(task: DmcTask, model, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`n` episode starts drawn in turn from one RandomState(seed): qpos [n, nq], qvel [n, nv]."""
    rng, data = np.random.RandomState(seed), mujoco.MjData(model)
    qpos, qvel = [], []
    for _ in range(n):
        episode_start(task, model, data, rng)
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    return np.array(qpos), np.array(qvel)


# --------------------------------------------------------------------------------------------
# Rewards: `make_reward(model)` resolves names to indices once and returns `view -> scalar`.


def _walker_reward(move_speed: float):
    stand_height = 1.2

    def make(model):
        torso = model.body("torso").id
        vel = model.sensor("torso_subtreelinvel").adr[0]

        def reward(v: PhysicsView):
            height = v.xpos[torso, 2]
            upright = (1 + v.xmat[torso, 2, 2]) / 2
            standing = tolerance(height, (stand_height, np.inf), margin=stand_height / 2)
            stand = (3 * standing + upright) / 4
            if move_speed == 0:
                return stand
            move = tolerance(
                v.sensordata[vel],
                (move_speed, np.inf),
                margin=move_speed / 2,
                value_at_margin=0.5,
                sigmoid="linear",
            )
            return stand * (5 * move + 1) / 6

        return reward

    return make


def _ball_in_cup_reward(model):
    target = model.site("target").id
    ball = model.body("ball").id
    target_size = model.site_size[target][[0, 2]].copy()
    ball_size = float(model.geom_size[model.geom("ball").id][0])

    def reward(v: PhysicsView):
        to_target = v.site_xpos[target][jnp.array([0, 2])] - v.xpos[ball][jnp.array([0, 2])]
        return jnp.all(jnp.abs(to_target) < target_size - ball_size).astype(jnp.float32)

    return reward


def _finger_spin_reward(model):
    vel = model.sensor("hinge_velocity").adr[0]

    def reward(v: PhysicsView):
        return (v.sensordata[vel] <= -15.0).astype(jnp.float32)

    return reward


def _cheetah_run_reward(model):
    vel = model.sensor("torso_subtreelinvel").adr[0]

    def reward(v: PhysicsView):
        return tolerance(
            v.sensordata[vel], (10.0, np.inf), margin=10.0, value_at_margin=0, sigmoid="linear"
        )

    return reward


def _cartpole_swingup_reward(model):
    slider = model.joint("slider").qposadr[0]

    def reward(v: PhysicsView):
        upright = (v.xmat[2:, 2, 2] + 1) / 2
        centered = (1 + tolerance(v.qpos[slider], margin=2)) / 2
        small_control = tolerance(v.ctrl, margin=1, value_at_margin=0, sigmoid="quadratic")[0]
        small_control = (4 + small_control) / 5
        small_velocity = (1 + tolerance(v.qvel[1:], margin=5).min()) / 2
        return upright.mean() * small_control * small_velocity * centered

    return reward


# --------------------------------------------------------------------------------------------
# Model edits.


def _finger_spin_physics(model):
    # dm_control's Spin sets this every episode; it is a constant, so set it once.
    model.dof_damping[model.joint("hinge").dofadr[0]] = 0.03


def _finger_spin_render(model):
    _finger_spin_physics(model)
    model.site_rgba[model.site("target").id, 3] = 0
    model.site_rgba[model.site("tip").id, 3] = 0


def _cartpole_physics(model):
    # MJX has no energy computation; energy never feeds back into the dynamics.
    model.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_ENERGY)


# --------------------------------------------------------------------------------------------
# Task table.


@dataclasses.dataclass(frozen=True)
class DmcTask:
    """Everything the env needs to know about one DMC task."""

    name: str  # registry name, "domain-task"
    xml_file: str  # file in dm_control/suite
    time_limit: float  # seconds per episode (1000 control steps for every task here)
    control_timestep: float | None  # None: one physics step per control step
    make_reward: Callable[[mujoco.MjModel], Callable[[PhysicsView], jnp.ndarray]]
    init_episode: Callable[[mujoco.MjModel, mujoco.MjData, np.random.RandomState], None]
    agent_bodies: tuple[str, ...]  # agent geoms = geoms of these bodies and their subtrees
    floor_geoms: tuple[str, ...]
    floor_alpha: float  # Distracting Control's ground-plane alpha
    camera: int = 0  # DrQ-v2's camera (0 for every task but quadruped)
    reward_range: tuple[float, float] = (0.0, 1.0)  # per control step
    edit_physics: Callable[[mujoco.MjModel], None] | None = None
    edit_render: Callable[[mujoco.MjModel], None] | None = None
    success_ends_episode: bool = False  # DMC episodes end at the time limit only

    @property
    def domain(self) -> str:
        return self.name.split("-")[0]

    def physics_model(self) -> mujoco.MjModel:
        """The model the physics steps (dm_control's options, task edits applied)."""
        model = load_model(self.xml_file)
        if self.edit_physics is not None:
            self.edit_physics(model)
        return model

    def render_model(self, mesh_faces: int = 0) -> mujoco.MjModel:
        """The model the render workers draw (physics edits plus visual ones). mesh_faces: no
        DMC task has a mesh to simplify (`RenderSettings.mesh_faces`), so anything but 0 is
        refused."""
        if mesh_faces:
            raise ValueError(
                f"{self.name} has no mesh to simplify: env.render.mesh_faces is for the kitchen; "
                "give 0"
            )
        model = load_model(self.xml_file)
        edit = self.edit_render or self.edit_physics
        if edit is not None:
            edit(model)
        return model

    def render_factory(self, mesh_faces: int = 0) -> Callable[[], mujoco.MjModel]:
        """Picklable zero-argument model factory for the render workers."""
        return functools.partial(render_model_fn, self.name, mesh_faces)

    def make_control(self, model: mujoco.MjModel) -> None:
        """DMC actions are the actuator controls (the physics backends' default)."""
        return None

    def n_sub_steps(self, model: mujoco.MjModel) -> int:
        if self.control_timestep is None:
            return 1
        n = self.control_timestep / model.opt.timestep
        if abs(n - round(n)) > 1e-6:
            raise ValueError(f"{self.name}: control timestep is not a multiple of the timestep")
        return int(round(n))

    def frames_per_episode(self, model: mujoco.MjModel) -> int:
        step = self.control_timestep or model.opt.timestep
        return int(round(self.time_limit / step))

    def agent_geom_ids(self, model: mujoco.MjModel) -> tuple[int, ...]:
        roots = {model.body(b).id for b in self.agent_bodies}
        ids = []
        for g in range(model.ngeom):
            body = model.geom_bodyid[g]
            while body != 0 and body not in roots:
                body = model.body_parentid[body]
            if body in roots:
                ids.append(g)
        return tuple(ids)

    def floor_geom_ids(self, model: mujoco.MjModel) -> tuple[int, ...]:
        return tuple(model.geom(name).id for name in self.floor_geoms)


def render_model_fn(task_name: str, mesh_faces: int = 0) -> mujoco.MjModel:
    """Picklable model factory for render workers: `functools.partial(render_model_fn, name, faces)`."""
    return TASKS[task_name].render_model(mesh_faces)


TASKS: dict[str, DmcTask] = {
    t.name: t
    for t in [
        *(
            DmcTask(
                name=f"walker-{gait}",
                xml_file="walker.xml",
                time_limit=25.0,
                control_timestep=0.025,
                make_reward=_walker_reward(speed),
                init_episode=_init_walker,
                agent_bodies=("torso",),
                floor_geoms=("floor",),
                floor_alpha=1.0,
            )
            for gait, speed in (("walk", 1.0), ("stand", 0.0), ("run", 8.0))
        ),
        DmcTask(
            name="ball_in_cup-catch",
            xml_file="ball_in_cup.xml",
            time_limit=20.0,
            control_timestep=0.02,
            make_reward=_ball_in_cup_reward,
            init_episode=_init_ball_in_cup,
            agent_bodies=("cup", "ball"),
            floor_geoms=("ground",),
            floor_alpha=0.3,
        ),
        DmcTask(
            name="finger-spin",
            xml_file="finger.xml",
            time_limit=20.0,
            control_timestep=0.02,
            make_reward=_finger_spin_reward,
            init_episode=_init_finger,
            agent_bodies=("proximal",),
            floor_geoms=("ground",),
            floor_alpha=0.3,
            edit_physics=_finger_spin_physics,
            edit_render=_finger_spin_render,
        ),
        DmcTask(
            name="cheetah-run",
            xml_file="cheetah.xml",
            time_limit=10.0,
            control_timestep=None,
            make_reward=_cheetah_run_reward,
            init_episode=_init_cheetah,
            agent_bodies=("torso",),
            floor_geoms=("ground",),
            floor_alpha=1.0,
        ),
        DmcTask(
            name="cartpole-swingup",
            xml_file="cartpole.xml",
            time_limit=10.0,
            control_timestep=None,
            make_reward=_cartpole_swingup_reward,
            init_episode=_init_cartpole_swingup,
            agent_bodies=("cart",),
            floor_geoms=("floor",),
            floor_alpha=1.0,
            edit_physics=_cartpole_physics,
        ),
    ]
}
