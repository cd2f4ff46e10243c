"""Env tests on the CPU physics backend with the real render pool (1 worker, tiny batches).

Covers: the registry, every registered task's reset/step contract, the JAX rewards against
dm_control's own `get_reward`, auto-reset semantics, frame stacking, mask variants and the
agent-geom rule. MJX against CPU MuJoCo lives in tests/test_physics.py.
"""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import envs
from envs import dmc

S, E = 1, 2


def _make(name, **kwargs):
    kwargs.setdefault("render", envs.RenderSettings(num_workers=1))
    return envs.make(name, num_seeds=S, envs_per_seed=E, backend="cpu", **kwargs)


def test_unknown_task_lists_valid_names():
    with pytest.raises(ValueError) as err:
        envs.make("walker-fly")
    for name in ("walker-walk", "ball_in_cup-catch", "finger-spin"):
        assert name in str(err.value)


def test_bad_arguments_name_valid_choices():
    with pytest.raises(ValueError, match="valid: mjx, cpu, auto"):
        envs.make("walker-walk", backend="tpu")
    with pytest.raises(ValueError, match="valid: true, noisy, approximate"):
        envs.make("walker-walk", mask="fuzzy")


def test_registry_has_the_required_tasks():
    assert {"walker-walk", "ball_in_cup-catch", "finger-spin"} <= set(envs.names())


def test_a_task_registered_by_a_builder_alone_asks_for_its_episode_length(monkeypatch):
    """A builder's task has no episode length before its env is built: a run's config check
    says to give env.episode_frames (a ValueError, which run.py prints as one line), and takes
    the task once it is given."""
    from configs import smoke
    from dear_jax import experiment

    monkeypatch.setitem(envs.registry._REGISTRY, "mine-reach", lambda **kwargs: None)
    with pytest.raises(ValueError, match="'mine-reach' was registered .* give env.episode_frames"):
        envs.frames_per_episode("mine-reach")
    config = smoke.get_config()
    config.env.task, config.env.episode_frames = "mine-reach", 0
    with pytest.raises(ValueError, match="give env.episode_frames"):
        experiment.validate(config)
    config.env.episode_frames = 200
    experiment.validate(config)


@pytest.mark.parametrize("name", sorted(dmc.TASKS))  # the kitchen: tests/test_kitchen.py
def test_task_resets_and_steps(name):
    with _make(name) as env:
        spec = env.spec
        assert spec.episode_steps * spec.action_repeat == 1000
        state, ts = env.reset(jax.random.key(1))
        rng = np.random.default_rng(0)
        steps = [ts]
        for _ in range(3):
            action = jnp.asarray(rng.uniform(-1, 1, (S, E, spec.action_dim)), jnp.float32)
            state, ts = env.step(state, action)
            steps.append(ts)
    expected = {
        "obs": (np.uint8, (S, E, 84, 84, 9)),
        "frame": (np.uint8, (S, E, 84, 84, 3)),
        "mask": (np.uint8, (S, E, 84, 84)),
        "true_mask": (np.uint8, (S, E, 84, 84)),
        "reward": (np.float32, (S, E)),
        "discount": (np.float32, (S, E)),
        "first": (np.bool_, (S, E)),
        "last": (np.bool_, (S, E)),
        "success": (np.float32, (S, E)),
    }
    for t, ts in enumerate(steps):
        for field, (dtype, shape) in expected.items():
            value = np.asarray(getattr(ts, field))
            assert value.dtype == dtype, (field, value.dtype)
            assert value.shape == shape, (field, value.shape)
        assert np.asarray(ts.first).all() == (t == 0)
        assert not np.asarray(ts.last).any()
        reward = np.asarray(ts.reward)
        assert np.isfinite(reward).all()
        lo, hi = dmc.TASKS[name].reward_range
        assert (reward >= lo * spec.action_repeat).all()
        assert (reward <= hi * spec.action_repeat).all()
        assert set(np.unique(np.asarray(ts.true_mask))) <= {0, 1}
        # The agent is in view in every frame.
        assert np.asarray(ts.true_mask).sum(axis=(2, 3)).min() > 20
        np.testing.assert_array_equal(np.asarray(ts.discount), 1.0)
    assert (np.asarray(steps[0].reward) == 0).all()
    assert np.isfinite(np.asarray(state.physics.qpos)).all()


# ---------------------------------------------------------------------------------------------
# Rewards against dm_control.


@pytest.fixture(scope="module")
def dm_suite():
    """dm_control's suite, loadable on MuJoCo 4.

    dm_control 1.0.50's index tables list 9 flex fields that MuJoCo 4 renamed; its named
    indexers fail on the first missing attribute. Dropping those entries (never used by these
    tasks) lets the suite load unchanged otherwise.
    """
    from dm_control.mujoco.wrapper.mjbindings import sizes

    probe = mujoco.MjModel.from_xml_string("<mujoco/>")
    for struct, obj in (("mjmodel", probe), ("mjdata", mujoco.MjData(probe))):
        for field in [f for f in sizes.array_sizes[struct] if not hasattr(obj, f)]:
            del sizes.array_sizes[struct][field]
    from dm_control import suite

    return suite


@pytest.mark.parametrize("name", sorted(dmc.TASKS))
def test_reward_equals_dm_control(name, dm_suite):
    domain, task_name = name.split("-")
    env = dm_suite.load(domain, task_name.replace("-", "_"), task_kwargs={"random": 0})
    physics = env.physics
    model = physics.model.ptr
    reward = jax.jit(dmc.TASKS[name].make_reward(model))
    rng = np.random.default_rng(0)
    env.reset()
    compared = []
    # Along a trajectory: the reward dm_control returns after each control step.
    for _ in range(40):
        ts = env.step(rng.uniform(-1, 1, env.action_spec().shape))
        ours = float(reward(dmc.view_from_mjdata(physics.data.ptr)))
        assert ours == pytest.approx(ts.reward, abs=1e-5)
        compared.append(ts.reward)
    # Random states (wide velocities) reach the branches a short trajectory may not.
    hits = _special_states(name, model)
    for i in range(60):
        with physics.reset_context():
            physics.data.qpos[:] = model.qpos0 + rng.normal(0, 0.5, model.nq)
            physics.data.qvel[:] = rng.normal(0, 8, model.nv)
            physics.data.ctrl[:] = rng.uniform(-1, 1, model.nu)
            if i < len(hits):
                hits[i](physics.data)
        expected = env.task.get_reward(physics)
        ours = float(reward(dmc.view_from_mjdata(physics.data.ptr)))
        assert ours == pytest.approx(float(expected), abs=1e-5), (i, expected, ours)
        compared.append(expected)
    compared = np.asarray(compared, float)
    # The comparison covered more than one reward value (not all zeros).
    assert len(np.unique(compared.round(4))) > 1


def _special_states(name, model):
    """State edits that put a sparse task into its rewarded branch."""

    def cup_ball_in(data):
        data.qpos[:] = 0
        data.qpos[model.joint("ball_z").qposadr[0]] = 0.35  # ball at the cup's target site

    def finger_spinning(data):
        data.qvel[model.joint("hinge").dofadr[0]] = -20.0

    def walker_upright(data):
        data.qpos[:] = 0
        data.qvel[:] = 0
        data.qvel[model.joint("rootx").dofadr[0]] = 1.5

    return {
        "ball_in_cup-catch": [cup_ball_in, cup_ball_in],
        "finger-spin": [finger_spinning],
        "walker-walk": [walker_upright],
        "walker-stand": [walker_upright],
        "walker-run": [walker_upright],
    }.get(name, [])


# ---------------------------------------------------------------------------------------------
# Agent geoms.


def test_agent_geom_rule():
    walker = dmc.TASKS["walker-walk"]
    m = walker.render_model()
    ids = walker.agent_geom_ids(m)
    assert len(ids) == m.ngeom - 1 and m.geom("floor").id not in ids
    cup = dmc.TASKS["ball_in_cup-catch"]
    m = cup.render_model()
    names = {m.geom(i).name for i in cup.agent_geom_ids(m)}
    assert names == {f"cup_part_{i}" for i in range(5)} | {"ball"}
    finger = dmc.TASKS["finger-spin"]
    m = finger.render_model()
    names = {m.geom(i).name for i in finger.agent_geom_ids(m)}
    assert names == {"proximal_decoration", "proximal", "distal", "fingertip"}
    # Spin hides the target and tip sites, as dm_control's Spin task does.
    assert m.site_rgba[m.site("target").id, 3] == 0 and m.site_rgba[m.site("tip").id, 3] == 0
    assert m.dof_damping[m.joint("hinge").dofadr[0]] == pytest.approx(0.03)


# ---------------------------------------------------------------------------------------------
# Episodes, stacking and masks (one env kept for the module).


@pytest.fixture(scope="module")
def finger_env():
    """Episodes of 20 frames (10 agent steps): the time limit ends an episode and the next step
    restarts it at any length (test_task_resets_and_steps checks each task's own, 1000 frames);
    test_auto_reset steps through a whole episode."""
    with _make("finger-spin", mask="noisy", mask_drop_prob=0.5, episode_frames=20) as env:
        yield env


def test_frame_stack_and_masks(finger_env):
    env = finger_env
    state, ts0 = env.reset(jax.random.key(0))
    obs0 = np.asarray(ts0.obs)
    frame0 = np.asarray(ts0.frame)
    for k in range(3):  # first timestep: the frame repeated
        np.testing.assert_array_equal(obs0[..., 3 * k : 3 * k + 3], frame0)
    action = jnp.full((S, E, env.spec.action_dim), 0.5, jnp.float32)
    state, ts1 = env.step(state, action)
    state, ts2 = env.step(state, action)
    obs2 = np.asarray(ts2.obs)
    np.testing.assert_array_equal(obs2[..., 0:3], frame0)  # oldest first
    np.testing.assert_array_equal(obs2[..., 3:6], np.asarray(ts1.frame))
    np.testing.assert_array_equal(obs2[..., 6:9], np.asarray(ts2.frame))
    # Noisy mask: a subset of the true mask, about half of it kept (p = 0.5).
    true, noisy = np.asarray(ts2.true_mask), np.asarray(ts2.mask)
    assert (noisy <= true).all()
    kept = noisy.sum() / true.sum()
    assert 0.35 < kept < 0.65


def test_auto_reset(finger_env):
    env = finger_env
    state, ts = env.reset(jax.random.key(3))
    n = env.spec.episode_steps
    action = jnp.zeros((S, E, env.spec.action_dim), jnp.float32)
    for t in range(1, n + 1):
        state, ts = env.step(state, action)
        assert bool(np.asarray(ts.last).all()) == (t == n), t
        assert not np.asarray(ts.first).any()
    np.testing.assert_array_equal(np.asarray(ts.discount), 1.0)  # time limit, not terminal
    before = np.asarray(state.physics.qpos).copy()
    # The step after `last` resets: first=True, reward 0, the action ignored.
    rng_state = env._rng.get_state()
    dis_state = env._distractor.rng.bit_generator.state
    state_a, ts_a = env.step(state, jnp.ones_like(action))
    env._rng.set_state(rng_state)
    env._distractor.rng.bit_generator.state = dis_state
    state_b, ts_b = env.step(state, -jnp.ones_like(action))
    for ts_x in (ts_a, ts_b):
        assert np.asarray(ts_x.first).all() and not np.asarray(ts_x.last).any()
        np.testing.assert_array_equal(np.asarray(ts_x.reward), 0.0)
    np.testing.assert_array_equal(np.asarray(ts_a.obs), np.asarray(ts_b.obs))
    np.testing.assert_array_equal(state_a.physics.qpos, state_b.physics.qpos)
    assert not np.allclose(state_a.physics.qpos, before)
    np.testing.assert_array_equal(state_a.step, 0)
    # Episode starts follow the task's rule: finger joints collision-free, qvel zero.
    np.testing.assert_array_equal(state_a.physics.qvel, 0.0)
    obs = np.asarray(ts_a.obs)
    np.testing.assert_array_equal(obs[..., 0:3], obs[..., 6:9])


def test_reset_is_reproducible_from_the_key():
    # Its pool sized by the batch: 2 envs at 2 per worker take one worker, whatever the cores.
    render = envs.RenderSettings(envs_per_worker=2)
    make = functools.partial(_make, "walker-walk", render=render)
    with make() as env:
        assert env._pool.num_workers == 1
        state_a, ts_a = env.reset(jax.random.key(7))
        state_b, ts_b = env.reset(jax.random.key(7))
        state_c, _ = env.reset(jax.random.key(8))
    np.testing.assert_array_equal(state_a.physics.qpos, state_b.physics.qpos)
    np.testing.assert_array_equal(np.asarray(ts_a.obs), np.asarray(ts_b.obs))
    assert not np.allclose(state_a.physics.qpos, state_c.physics.qpos)
    # The two envs of a batch start differently.
    assert not np.allclose(state_a.physics.qpos[0, 0], state_a.physics.qpos[0, 1])


def test_dynamic_distractions_move_once_per_frame():
    """Dynamic distractions move as the Distracting Control Suite's under an action repeat: once
    per frame, so a background video advances action_repeat frames per agent step (here from
    the middle of videos long enough not to bounce)."""
    render = envs.RenderSettings(envs_per_worker=2)
    for repeat in (1, 2):
        with _make(
            "walker-walk", render=render, distraction="medium", dynamic=True, action_repeat=repeat
        ) as env:
            dis = env._distractor
            state, _ = env.reset(jax.random.key(0))
            dis.frame[:] = dis.lengths[dis.video] // 2
            dis.direction[:] = 1
            start = dis.frame.copy()
            action = jnp.zeros((S, E, env.spec.action_dim))
            for _ in range(3):
                state, _ = env.step(state, action)
            np.testing.assert_array_equal(dis.frame - start, 3 * repeat)


def test_cpu_physics_steps_on_the_env_thread(finger_env):
    """With CPU physics, step_async hands the physics to the env thread and returns at once: the
    caller (the trainer, dispatching updates meanwhile) never waits for the action or the step."""
    import threading

    env = finger_env
    state, _ = env.reset(jax.random.key(0))
    threads, release = [], threading.Event()
    step = env.physics.step

    def recording_step(*args):
        threads.append(threading.current_thread())
        release.wait(timeout=30)  # holds the physics until the caller has got its future
        return step(*args)

    env.physics.step = recording_step
    try:
        future = env.step_async(state, jnp.zeros((S, E, env.spec.action_dim), jnp.float32))
        assert not future.done()
        release.set()
        _, ts = future.result()
    finally:
        del env.physics.step
    assert len(threads) == 1 and threads[0] is not threading.current_thread()
    assert not np.asarray(ts.first).any()
