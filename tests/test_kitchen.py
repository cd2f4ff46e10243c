"""Franka Kitchen (envs/kitchen.py): model, collision model, camera, masks, scripted successes.

One MJX compile for the whole file (~35 s of CPU): the module fixture `light` steps a
kitchen-light Env of 2 envs on CPU MuJoCo with closed-loop scripted joint commands (env 0 flips
the light switch, env 1 pushes the fingers down into the counter), then replays the same
actions on the MJX backend. Scripts are joint-space waypoints (found offline with inverse
kinematics) tracked by `_track`: action = clip((waypoint - q) / (2 * 0.08), -1, 1), fingers
closed. Stated tolerances (measured values in the test bodies' comments):
- MJX (4 Newton / 3 line-search iterations) against CPU MuJoCo (the XML's 100 / 50) on the
  same actions: before the robot touches anything the arm joints within 1e-4 rad and all of
  qpos within 5 mm; pushing the lever, the switch angle within 0.2 rad and both reaching the
  goal within 2 agent steps of each other. The push-down is not compared: the hand scrapes
  along the counter under the arm's full torque, and the sliding differs between MJX's and
  MuJoCo's contact sets (the hands end ~7 cm apart); it checks penetration on each backend;
- counter: no robot-scene contact deeper than 5 mm over the push-down on either backend.

The envs draw "fast" pictures (no shadows, reflections or multisampling): the tests read the
masks, which MuJoCo's flat-colour segmentation pass draws the same under every quality
(envs/render.py; tests/test_render.py checks it), and RGB frames only to compare simplified
meshes with the shipped ones; the default effects cost ~7x on llvmpipe (~45 s of this file's
rollouts).
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import envs  # noqa: E402
from envs import dmc, kitchen, physics  # noqa: E402
from envs.labels import LABEL_AGENT  # noqa: E402
from envs.render import TileRenderer  # noqa: E402

S, E = 1, 2
STEP = kitchen.ACTION_SCALE * kitchen.CONTROL_TIMESTEP

# Joint-space waypoints of the 7 arm joints (inverse kinematics of the end-effector site).
SWITCH = [  # hand pointing forward: right of the lever, at its height, then sweep left
    [-0.778, -1.196, 1.255, -2.667, 0.081, 1.945, 0.977],
    [-1.389, -1.058, 1.504, -2.212, 0.048, 2.056, 1.009],
    [-1.432, -1.353, 1.515, -1.582, 0.205, 1.445, 1.145],
]
PUSH_DOWN = [  # hand pointing down above the left counter, then 10 cm into it
    [-1.361, -0.989, 2.481, -1.707, 0.846, 0.817, 0.853],
    [-1.577, -1.619, 2.657, -1.118, 0.935, 0.955, 0.947],
]
KETTLE = [  # hand pointing down behind the kettle, lowered, then pushing it forwards
    [0.197, -0.336, 1.224, -2.987, 0.881, 1.158, 0.631],
    [0.805, 0.74, 0.318, -2.689, 0.695, 1.907, 0.41],
    [0.773, 0.713, 0.07, -2.496, 0.603, 1.652, 0.255],
    [0.732, 0.814, -0.133, -2.145, 0.482, 1.362, 0.189],
]
HOLD = 15  # agent steps per waypoint at most


class _Track:
    """Closed-loop waypoint tracker for one env: qpos [nq] -> action [9]."""

    def __init__(self, waypoints):
        self.waypoints, self.index, self.steps = np.asarray(waypoints), 0, 0

    def __call__(self, qpos):
        target = self.waypoints[self.index]
        error = target - qpos[:7]
        last = self.index == len(self.waypoints) - 1
        if not last and (np.abs(error).max() < 0.05 or self.steps >= HOLD):
            self.index, self.steps = self.index + 1, 0
            error = self.waypoints[self.index] - qpos[:7]
        self.steps += 1
        return np.concatenate([np.clip(error / STEP, -1, 1), [-1.0, -1.0]]).astype(np.float32)


def _make(name, backend, mesh_faces=0):
    return envs.make(
        name,
        num_seeds=S,
        envs_per_seed=E,
        backend=backend,
        render=envs.RenderSettings(num_workers=1, quality="fast", mesh_faces=mesh_faces),
    )


def _record(env, state, ts, out):
    out["qpos"].append(np.asarray(env.physics.qpos(state.physics), np.float64).copy())
    for k in ("reward", "last", "success", "discount", "first"):
        out[k].append(np.asarray(getattr(ts, k)).copy())
    out["frames"].append((np.asarray(ts.frame), np.asarray(ts.true_mask)))


def _rollout(env, policy=None, actions=None, steps=60):
    """Scripted (policy(qpos [S,E,nq]) -> actions) or replayed rollout; stops at env 0's success."""
    out = {k: [] for k in ("qpos", "reward", "last", "success", "discount", "first", "frames")}
    out["actions"] = []
    state, ts = env.reset(jax.random.key(0))
    _record(env, state, ts, out)
    for t in range(steps if actions is None else len(actions)):
        qpos = np.asarray(env.physics.qpos(state.physics))
        action = policy(qpos) if actions is None else actions[t]
        state, ts = env.step(state, jnp.asarray(action))
        out["actions"].append(action)
        _record(env, state, ts, out)
        if actions is None and out["success"][-1][0, 0]:
            break
    return {k: np.array(v) if k != "frames" else v for k, v in out.items()}


@pytest.fixture(scope="module", autouse=True)
def mjx_full_optimisation():
    """The MJX programs of this file at XLA's full optimisation (the test processes compile at
    level 0, conftest.py): a kitchen agent step of 2 envs took 1.9 s at level 0 against 0.7 s,
    and the rollouts step it dozens of times. Elsewhere (tests/test_physics.py: a few steps of
    walker and finger) level 0 costs less, compile included."""
    options = physics._compiler_options

    def full_optimisation():
        base = options()
        return None if base is None else {**base, "xla_backend_optimization_level": 3}

    physics._compiler_options = full_optimisation
    yield
    physics._compiler_options = options


@pytest.fixture(scope="module")
def light():
    tracks = [_Track(SWITCH), _Track(PUSH_DOWN)]

    def policy(qpos):
        return np.stack([tracks[e](qpos[0, e]) for e in range(E)])[None]

    with _make("kitchen-light", "cpu") as env:
        cpu = _rollout(env, policy)
    with _make("kitchen-light", "mjx") as env:
        # Two extra steps of the last action: MJX may reach the goal a step later.
        extra = np.repeat(cpu["actions"][-1:], 2, axis=0)
        mjx_ = _rollout(env, actions=np.concatenate([cpu["actions"], extra]))
    return {"cpu": cpu, "mjx": mjx_}


@pytest.fixture(scope="module")
def physics_model():
    return kitchen.build_physics_model()


# --------------------------------------------------------------------------------------------
# The model.


def test_registry_and_spec():
    assert {"kitchen-light", "kitchen-kettle"} <= set(envs.names())
    task = kitchen.TASKS["kitchen-kettle"]
    model = task.physics_model()
    assert (model.nq, model.nv, model.nu) == (30, 29, 9)
    assert task.n_sub_steps(model) == 40 and model.opt.timestep == 0.002
    assert task.frames_per_episode(model) == 280
    assert kitchen.scene_dir().startswith(os.path.dirname(os.path.dirname(mujoco.__file__)))
    assert not os.path.exists(os.path.join(os.path.dirname(envs.__file__), "assets"))


def test_collision_model_is_mjx_ready_and_keeps_the_mass(physics_model):
    from mujoco import mjx
    from mujoco.mjx._src import collision_driver

    shipped = kitchen.load_spec().compile()
    with pytest.raises(NotImplementedError, match="collisions not implemented"):
        mjx.put_model(shipped, impl="jax")
    mjx.put_model(physics_model, impl="jax")
    m = physics_model
    np.testing.assert_array_equal(m.body_mass, shipped.body_mass)
    np.testing.assert_array_equal(m.body_inertia, shipped.body_inertia)
    np.testing.assert_array_equal(m.body_ipos, shipped.body_ipos)
    robot = set(kitchen.robot_body_ids(m))
    kettle = m.body(kitchen.KETTLE_BODY).id
    kinds = set()
    for g1, g2, _ in collision_driver.geom_pairs(m):
        b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
        kinds.add(
            tuple(
                sorted(
                    "robot" if b in robot else "kettle" if b == kettle else "scene"
                    for b in (b1, b2)
                )
            )
        )
    assert kinds == {("robot", "scene"), ("kettle", "robot"), ("kettle", "scene")}
    names = {m.body(m.geom_bodyid[g]).name for g in range(m.ngeom) if m.geom_contype[g]}
    assert {"lightswitchroot", "kettleroot", "counters", "ovenroot", "hoodroot"} <= names
    assert {"panda0_leftfinger", "panda0_rightfinger", "panda0_link7"} <= names


def test_geoms_without_contacts_are_left_out_and_change_no_state(physics_model):
    spec, _ = kitchen.collision_spec()
    full = spec.compile()  # every shipped geom kept, the same contacts
    colliding = [g for g in range(full.ngeom) if full.geom_contype[g] or full.geom_conaffinity[g]]
    assert physics_model.ngeom == len(colliding) < full.ngeom
    control = kitchen.TASKS["kitchen-kettle"].make_control(physics_model)
    robot = set(kitchen.robot_body_ids(physics_model))
    track = _Track(PUSH_DOWN)  # the hand 10 cm into the counter: robot-scene contacts
    datas = [mujoco.MjData(m) for m in (full, physics_model)]
    for d in datas:
        d.qpos[:] = kitchen.INIT_QPOS
    robot_contacts = 0
    for _ in range(30):  # agent steps of 40 physics steps
        action = track(datas[1].qpos)
        for model, data in zip((full, physics_model), datas):
            data.ctrl[:] = control(data.qpos, action, np)
            mujoco.mj_step(model, data, 40)
        np.testing.assert_array_equal(datas[0].qpos, datas[1].qpos)
        np.testing.assert_array_equal(datas[0].qvel, datas[1].qvel)
        np.testing.assert_array_equal(datas[0].efc_force, datas[1].efc_force)
        bodies = physics_model.geom_bodyid
        robot_contacts += sum(
            (bodies[c.geom1] in robot) != (bodies[c.geom2] in robot)
            for c in datas[1].contact[: datas[1].ncon]
        )
    assert robot_contacts > 0  # the robot's contact paths ran too


def test_robot_primitives_contain_the_shipped_collision_meshes(physics_model):
    shipped = kitchen.load_spec().compile()
    d_s, d_m = mujoco.MjData(shipped), mujoco.MjData(physics_model)
    for model, data in ((shipped, d_s), (physics_model, d_m)):
        data.qpos[:] = kitchen.INIT_QPOS
        mujoco.mj_kinematics(model, data)
    for body in ("panda0_link5", "panda0_link6", "panda0_link7"):
        b = shipped.body(body).id
        meshes = [
            g
            for g in range(shipped.ngeom)
            if shipped.geom_bodyid[g] == b and shipped.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        ]
        prims = [
            g
            for g in range(physics_model.ngeom)
            if physics_model.geom_bodyid[g] == b and physics_model.geom_contype[g]
        ]
        for g in meshes:
            if not shipped.geom_contype[g]:
                continue
            verts = kitchen.mesh_vertices(shipped, g)
            world = d_s.geom_xpos[g] + verts @ d_s.geom_xmat[g].reshape(3, 3).T
            inside = np.zeros(len(world), bool)
            for p in prims:
                local = (world - d_m.geom_xpos[p]) @ d_m.geom_xmat[p].reshape(3, 3)
                size = physics_model.geom_size[p]
                if physics_model.geom_type[p] == mujoco.mjtGeom.mjGEOM_BOX:
                    inside |= (np.abs(local) <= size + 1e-6).all(1)
                else:
                    axial = np.clip(local[:, 2], -size[1], size[1])
                    gap = local - np.stack([0 * axial, 0 * axial, axial], 1)
                    inside |= np.linalg.norm(gap, axis=1) <= size[0] + 1e-6
            assert inside.all(), f"{body}: {(~inside).sum()} collision-mesh vertices outside"


def test_reference_camera_equals_the_free_camera():
    model = kitchen.build_render_model()
    data = mujoco.MjData(model)
    data.qpos[:] = kitchen.INIT_QPOS
    mujoco.mj_forward(model, data)
    free = mujoco.MjvCamera()
    free.type = mujoco.mjtCamera.mjCAMERA_FREE
    free.lookat[:] = kitchen.CAMERA_LOOKAT
    free.distance, free.azimuth = kitchen.CAMERA_DISTANCE, kitchen.CAMERA_AZIMUTH
    free.elevation = kitchen.CAMERA_ELEVATION
    with mujoco.Renderer(model, 84, 84) as renderer:
        renderer.update_scene(data, free)
        a = renderer.render()
        renderer.update_scene(data, kitchen.CAMERA_NAME)
        b = renderer.render()
    np.testing.assert_array_equal(a, b)


def test_action_is_a_joint_velocity(physics_model):
    control = kitchen.TASKS["kitchen-light"].make_control(physics_model)
    qpos = kitchen.INIT_QPOS.copy()
    action = np.array([0.5, -1, 1, 0, 0, 0, 0, 3.0, -3.0])  # out-of-range entries clip to +-1
    ctrl = control(qpos, action, np)
    expected = qpos[:9] + 0.16 * np.clip(action, -1, 1)
    low, high = kitchen.robot_position_bounds()
    np.testing.assert_allclose(ctrl, np.clip(expected, low, high))
    np.testing.assert_allclose(ctrl[7:], [0.04, 0.0])  # finger bounds [0, 0.04]
    np.testing.assert_allclose(
        np.asarray(control(jnp.asarray(qpos), jnp.asarray(action))), ctrl, atol=1e-6
    )
    # Joint 1 (a vertical axis: no gravity load), 0.5 -> 1 rad/s for 5 agent steps (0.4 rad):
    # the servo covers about half (measured 0.20 rad), as in D4RL: damping 100 over kp 870 is
    # a 0.115 s lag, longer than the 0.08 s step.
    data = mujoco.MjData(physics_model)
    data.qpos[:] = kitchen.INIT_QPOS
    for _ in range(5):
        data.ctrl[:] = control(data.qpos, np.array([0.5, 0, 0, 0, 0, 0, 0, 0, 0]), np)
        mujoco.mj_step(physics_model, data, 40)
    moved = data.qpos[0] - kitchen.INIT_QPOS[0]
    assert 0.15 < moved < 0.3, moved


def test_reward_is_the_goal_distance_threshold(physics_model):
    for name, task in kitchen.TASKS.items():
        reward = jax.jit(task.make_reward(physics_model))
        view = lambda q: kitchen.PhysicsView(  # noqa: E731
            qpos=jnp.asarray(q, jnp.float32), qvel=None, ctrl=None, xpos=None, xmat=None,
            site_xpos=None, sensordata=None,
        )  # fmt: skip
        start = kitchen.INIT_QPOS.copy()
        assert float(reward(view(start))) == 0.0, name
        at_goal = start.copy()
        at_goal[list(task.object_qpos)] = task.goal
        assert float(reward(view(at_goal))) == 1.0, name
        near = at_goal.copy()
        near[task.object_qpos[0]] += 0.29
        assert float(reward(view(near))) == 1.0, name
        near[task.object_qpos[0]] += 0.02
        assert float(reward(view(near))) == 0.0, name


# --------------------------------------------------------------------------------------------
# Scripted rollouts on both backends.


def test_reset_and_steps_are_finite_on_both_backends(light):
    for backend in ("cpu", "mjx"):
        run = light[backend]
        t = int(np.flatnonzero(run["last"][:, 0, 0])[0])  # env 0's success: a reset follows
        assert np.isfinite(run["qpos"]).all(), backend
        np.testing.assert_allclose(run["qpos"][0, 0, 0], kitchen.INIT_QPOS, atol=1e-6)
        assert run["first"][0].all() and not run["first"][1 : t + 1].any(), backend
    # MJX ran on past its success: env 0 restarted alone, env 1 went on.
    run = light["mjx"]
    t = int(np.flatnonzero(run["last"][:, 0, 0])[0])
    assert t + 1 < len(run["first"])
    np.testing.assert_array_equal(run["first"][t + 1], [[True, False]])
    np.testing.assert_allclose(run["qpos"][t + 1, 0, 0], kitchen.INIT_QPOS, atol=1e-6)
    assert run["reward"][t + 1, 0, 0] == 0.0 and not run["last"][t + 1, 0, 0]


def test_scripted_switch_reaches_the_goal_and_ends_the_episode(light):
    run, task = light["cpu"], kitchen.TASKS["kitchen-light"]
    reward, last = run["reward"][:, 0, 0], run["last"][:, 0, 0]
    t = int(np.flatnonzero(reward)[0])
    assert t == len(reward) - 1 < 60  # the script stops at the first success
    assert reward[t] == 1.0 and last[t] and run["success"][t, 0, 0] == 1.0
    assert run["discount"][t, 0, 0] == 0.0 and (run["discount"][:t, 0, 0] == 1.0).all()
    assert not last[:t].any() and (reward[:t] == 0).all()
    distance = task.goal_distance(run["qpos"][:, 0, 0])
    assert distance[t] < kitchen.SUCCESS_THRESHOLD <= distance[:t].min()
    assert run["qpos"][t, 0, 0, 17] < -0.35  # the switch turned (goal -0.69, 0.3 away)


def _first_robot_contact(model, qposes):
    """Index of the first state of qposes [T, nq] where the robot touches anything."""
    data = mujoco.MjData(model)
    robot = set(kitchen.robot_body_ids(model))
    for t, q in enumerate(qposes):
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        for c in data.contact[: data.ncon]:
            if (model.geom_bodyid[c.geom1] in robot) != (model.geom_bodyid[c.geom2] in robot):
                return t
    return len(qposes)


def test_mjx_follows_cpu_on_the_scripted_rollout(light, physics_model):
    cpu, mjx_ = light["cpu"], light["mjx"]
    hits = np.flatnonzero(mjx_["success"][:, 0, 0])
    t_cpu = len(cpu["actions"])
    # Both flip the switch, within 2 agent steps of each other (measured: CPU 35, MJX 33).
    assert len(hits) and abs(int(hits[0]) - t_cpu) <= 2, (hits, t_cpu)
    t = min(t_cpu, int(hits[0]))
    q_cpu, q_mjx = cpu["qpos"][: t + 1, 0], mjx_["qpos"][: t + 1, 0]
    for e in range(E):
        # Free motion, until the robot first touches something (steps 21 and 7): the arm
        # agrees to 2e-6 rad, the rest (the kettle settling on the oven) to 1.9 mm.
        free = _first_robot_contact(physics_model, q_cpu[:, e])
        assert free >= 5, free
        assert np.abs(q_mjx[:free, e, :9] - q_cpu[:free, e, :9]).max() <= 1e-4, e
        assert np.abs(q_mjx[:free, e] - q_cpu[:free, e]).max() <= 5e-3, e
    # Pushing the lever: the switch angle within 0.2 rad (measured 0.115) up to the success.
    switch = np.abs(q_mjx[:, 0, 17] - q_cpu[:, 0, 17]).max()
    assert switch <= 0.2, switch


def _deepest_robot_contact(model, qposes):
    """Most negative distance of a robot-scene contact over states qposes [T, nq] (m)."""
    data = mujoco.MjData(model)
    robot = set(kitchen.robot_body_ids(model))
    deepest = 0.0
    for q in qposes:
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        for c in data.contact[: data.ncon]:
            if (model.geom_bodyid[c.geom1] in robot) != (model.geom_bodyid[c.geom2] in robot):
                deepest = min(deepest, c.dist)
    return deepest


def test_counter_stops_the_hand(light, physics_model):
    fingers = [physics_model.body(b).id for b in kitchen.FINGER_BODIES]
    data = mujoco.MjData(physics_model)
    for backend in ("cpu", "mjx"):
        qposes = light[backend]["qpos"][:, 0, 1]
        depth = _deepest_robot_contact(physics_model, qposes)
        assert depth > -0.005, (backend, depth)
        data.qpos[:] = qposes[-1]
        mujoco.mj_kinematics(physics_model, data)
        # The fingers rest on the counter top (z 1.60) although the target is 10 cm below it.
        assert abs(data.xpos[fingers, 2].min() - 1.60) < 0.15, backend
        assert depth < 0, backend  # they do touch it


def test_mask_is_exactly_the_robot(light):
    model = kitchen.build_render_model()
    robot = set(kitchen.robot_body_ids(model))
    data = mujoco.MjData(model)
    run = light["cpu"]
    with mujoco.Renderer(model, 84, 84) as renderer:
        renderer.enable_segmentation_rendering()
        for t in (0, len(run["qpos"]) - 1):
            for e in range(E):
                data.qpos[:] = run["qpos"][t, 0, e]
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, kitchen.CAMERA_NAME)
                seg = renderer.render()
                is_geom = seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM
                bodies = model.geom_bodyid[np.where(is_geom, seg[..., 0], 0)]
                expected = is_geom & np.isin(bodies, list(robot))
                frame, mask = run["frames"][t]
                np.testing.assert_array_equal(mask[0, e], expected.astype(np.uint8))
                assert 150 < expected.sum() < 0.5 * 84 * 84  # the robot is visible, not everything
    assert LABEL_AGENT == 2


def test_simplified_meshes_draw_nearly_the_same_frames(light):
    """mesh_faces=4000: the arm's nine visual meshes (134k faces) simplified, nothing else; the
    scripted rollout's frames (start, end; both envs) within a level of 255 per pixel on average
    (0.52 over 32 random states, benchmarks/results/render_kitchen_mesh_faces_cpu.json) and the
    masks within 0.1% of their pixels (0.02% there)."""
    shipped = kitchen.build_render_model()
    simple = kitchen.TASKS["kitchen-light"].render_factory(4000)()
    assert (simple.nmesh, simple.ngeom, simple.nbody) == (
        shipped.nmesh,
        shipped.ngeom,
        shipped.nbody,
    )
    viz = [i for i in range(shipped.nmesh) if shipped.mesh_facenum[i] > 4000]
    assert len(viz) == 9 and all(shipped.mesh(i).name.endswith("_viz") for i in viz)
    assert shipped.mesh_facenum[viz].sum() > 130_000
    assert all(3_000 < simple.mesh_facenum[i] <= 4_000 for i in viz)
    rest = np.setdiff1d(np.arange(shipped.nmesh), viz)
    np.testing.assert_array_equal(simple.mesh_facenum[rest], shipped.mesh_facenum[rest])

    run = light["cpu"]
    qpos = np.concatenate([run["qpos"][0, 0], run["qpos"][-1, 0]])  # [4, nq]
    with _make("kitchen-light", "cpu", mesh_faces=4000) as env:
        _, ts = env.reset(jax.random.key(0))
        # The env's pool draws the simplified meshes: its first frames differ from the shipped
        # meshes' a little, and not at all is a pool that ignored the setting.
        first, first_mask = run["frames"][0]
        gap = np.abs(np.asarray(ts.frame, np.int16) - first).mean()
        assert 0 < gap < 1.0
        assert (np.asarray(ts.true_mask) != first_mask).mean() < 0.001
        rgb, labels = env._pool.render(qpos)
    settings = envs.RenderSettings(num_workers=1, quality="fast")
    task = kitchen.TASKS["kitchen-light"]
    ref = TileRenderer(
        shipped,
        camera=task.camera,
        agent_geom_ids=task.agent_geom_ids(shipped),
        floor_geom_ids=task.floor_geom_ids(shipped),
        settings=settings,
    )
    ref_rgb, ref_labels = np.zeros_like(rgb), np.zeros_like(labels)
    ref.render(qpos, ref_rgb, ref_labels)
    ref.close()
    assert 0 < np.abs(rgb.astype(np.int16) - ref_rgb).mean() < 1.0
    assert (labels != ref_labels).mean() < 0.001


def test_mesh_faces_is_checked():
    for faces in (-1, 3, 999):
        with pytest.raises(ValueError, match=f"mesh_faces must be 0 .* or >= 1000, got {faces}"):
            envs.RenderSettings(mesh_faces=faces)
    assert kitchen.build_render_model(0).nmeshface == kitchen.load_spec().compile().nmeshface
    with pytest.raises(ValueError, match="walker-walk has no mesh to simplify"):
        dmc.TASKS["walker-walk"].render_model(4000)


def test_scripted_kettle_push_reaches_the_goal():
    track = _Track(KETTLE)
    task = kitchen.TASKS["kitchen-kettle"]

    def policy(qpos):
        return np.stack([track(qpos[0, 0]), np.zeros(9, np.float32)])[None]

    with _make("kitchen-kettle", "cpu") as env:
        run = _rollout(env, policy, steps=70)
    t = int(np.flatnonzero(run["reward"][:, 0, 0])[0])
    assert run["last"][t, 0, 0] and run["success"][t, 0, 0] == 1.0
    assert not run["reward"][:, 0, 1].any()  # the idle env got nothing
    kettle = run["qpos"][t, 0, 0, 23:26]
    assert kettle[1] > 0.4 and abs(kettle[2] - 1.62) < 0.02  # pushed forwards, still upright
    assert task.goal_distance(run["qpos"][t, 0, 0]) < kitchen.SUCCESS_THRESHOLD


@pytest.mark.parametrize("task", ["light", "kettle"])
def test_configs_validate(task):
    from configs import paper
    from dear_jax import experiment

    for method in ("dear", "drqv2", "sear", "ted"):
        config = paper.get_config(f"{task},{method}")
        experiment.validate(config)
        assert config.env.task == f"kitchen-{task}" and config.agent.method == method
        assert config.env.action_repeat == 1 and config.env.episode_frames == 0


def test_evaluation_counts_each_envs_first_episode():
    """Kitchen episodes end at different steps; dear_jax.evaluator.evaluate must still stop, and
    count the returns, successes and latent cosines of each env's first episode only."""
    import types

    from dear_jax import evaluator

    ends, wins = np.array([[2, 4, 3]]), np.array([[True, False, True]])

    class FakeEnv:
        shape = (1, 3)
        spec = types.SimpleNamespace(has_success=True)

        def _ts(self, step):
            end = step == ends
            # After its end an env restarts and would score 5 a step: none of it may count.
            reward = np.where(step > ends, 5.0, np.where(end & wins, 1.0, 0.0))
            ts = types.SimpleNamespace(
                obs=jnp.zeros((1, 3, 4)), frame=None, true_mask=None,
                reward=jnp.asarray(reward, jnp.float32),
                success=jnp.asarray(end & wins, jnp.float32),
            )  # fmt: skip
            return types.SimpleNamespace(step=step, last=end), ts

        def reset(self, key):
            return self._ts(np.zeros((1, 3), int))

        def step(self, state, action):
            assert state.step.max() < 20, "evaluate did not stop"
            return self._ts(state.step + 1)

    # The observations' cosines per env: 3 + 5 + 4 of first episodes (steps 0 to its end),
    # then, once an env has restarted, 9 (must not count) until the last env's episode ends.
    calls = []

    def step(params, obs):
        t = len(calls)
        calls.append(t)
        cos = np.where(t > ends, 9.0, np.array([[-0.2, 0.1, 0.4]]))
        return jnp.zeros((1, 3, 9)), jnp.asarray(cos, jnp.float32), jnp.zeros((4, 4))

    metrics, _ = evaluator.evaluate(FakeEnv(), step, None, None, video=False)
    np.testing.assert_allclose(metrics["episode_return"], [2 / 3])
    np.testing.assert_allclose(metrics["success"], [2 / 3])
    assert len(calls) == 5  # the last env's episode: steps 0-4
    want = (3 * -0.2 + 5 * 0.1 + 4 * 0.4) / 12
    np.testing.assert_allclose(metrics["cos_agent_env"], [want], rtol=1e-6)
    np.testing.assert_allclose(metrics["abs_cos_agent_env"], [(0.6 + 0.5 + 1.6) / 12], rtol=1e-6)
