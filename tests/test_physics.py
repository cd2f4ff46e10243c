"""MJX against CPU MuJoCo (dm_control's own solver options) on a fixed action sequence.

The MJX backend runs with the default tuned `SolverSettings` (4 Newton and 3 line-search
iterations instead of the XML's 100 and 50); this test is the evidence that the task still behaves. Stated
tolerances, walker-walk, 4 envs from dm_control's episode-start distribution, smooth fixed
actions, 25 agent steps (50 control steps, 500 physics steps):
- states: max |qpos difference| <= 0.05 over the first 5 agent steps (measured 0.001);
- rewards: every per-step reward within 0.15 of CPU MuJoCo's (measured 0.027), and each
  env's 25-step return within 5% (measured 0.4%).
(Measured with the starts of `dmc.episode_start`; with the walker's legs started straight the
same check measured 0.01, 0.085 and 2%.)
Later divergence is expected: the walker is chaotic once it falls, at any solver setting.
One MJX compile (~40 s on a CPU): keep this file to one compiled step function.
"""

import dataclasses
import sys
import threading

import mujoco
import numpy as np
import pytest

from envs import dmc, kitchen
from envs.physics import CpuPhysics, MjxPhysics, SolverSettings, make_physics

T, NUM_ENVS = 25, 4


def _actions(nu):
    t = np.arange(T)[:, None, None, None] * 0.05
    phase = np.arange(NUM_ENVS)[None, None, :, None]
    freq = np.arange(1, nu + 1) / nu
    return np.sin(2 * np.pi * freq * t + phase).astype(np.float32)  # [T, 1, N, nu]


@pytest.fixture(scope="module")
def walker_rollouts():
    task = dmc.TASKS["walker-walk"]
    model = task.physics_model()
    reward = task.make_reward(model)
    kwargs = dict(n_sub_steps=task.n_sub_steps(model), action_repeat=2)
    qpos, qvel = (x[None] for x in dmc.episode_starts(task, model, NUM_ENVS))  # [1, n, ...]
    actions = _actions(model.nu)
    out = {}
    for name, phys in [
        ("cpu", CpuPhysics(model, reward, **kwargs)),
        ("mjx", MjxPhysics(model, reward, solver=SolverSettings(), **kwargs)),
    ]:
        state = phys.init(qpos, qvel)
        rewards, qposes = [], []
        for a in actions:
            state, r = phys.step(state, a)
            rewards.append(np.asarray(r))
            qposes.append(np.asarray(phys.qpos(state)))
        out[name] = np.array(rewards), np.array(qposes)
    return out


def test_mjx_states_close_to_cpu(walker_rollouts):
    (_, q_cpu), (_, q_mjx) = walker_rollouts["cpu"], walker_rollouts["mjx"]
    assert np.isfinite(q_mjx).all()
    assert np.abs(q_mjx[:5] - q_cpu[:5]).max() <= 0.05
    # The bodies moved: the comparison is not of two resting states.
    assert np.abs(q_cpu[-1] - q_cpu[0]).max() > 0.3


def test_mjx_rewards_close_to_cpu(walker_rollouts):
    (r_cpu, _), (r_mjx, _) = walker_rollouts["cpu"], walker_rollouts["mjx"]
    assert np.abs(r_mjx - r_cpu).max() <= 0.15
    ret_cpu, ret_mjx = r_cpu.sum(0), r_mjx.sum(0)
    np.testing.assert_allclose(ret_mjx, ret_cpu, rtol=0.05)
    assert (ret_cpu > 1.0).all()  # rewards are not trivially zero


@pytest.mark.parametrize("task", [dmc.TASKS["walker-walk"], kitchen.TASKS["kitchen-kettle"]])
def test_cpu_threads_step_each_env_as_one_thread_does(task):
    """2 seeds x 4 envs split over 3 threads (unequal blocks) step bit for bit as on one thread,
    rewards and every state field, through an episode restart in some envs; the kitchen runs
    its joint-velocity control on the threads too."""
    model = task.physics_model()
    kwargs = dict(
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=2,
        control=task.make_control(model),
    )
    one = CpuPhysics(model, task.make_reward(model), threads=1, **kwargs)
    three = CpuPhysics(model, task.make_reward(model), threads=3, **kwargs)
    stepped_on = set()  # the threads that ran three's control steps
    control_step = three._control_step
    three._control_step = lambda d: (
        stepped_on.add(threading.current_thread().name),
        control_step(d),
    )
    try:
        rng = np.random.RandomState(1)
        shape = (2, 4)
        qpos = model.qpos0 + 0.05 * rng.randn(*shape, model.nq)
        qvel = 0.1 * rng.randn(*shape, model.nv)
        states = [p.init(qpos, qvel) for p in (one, three)]
        reset = np.zeros(shape, bool)
        reset[0, 1] = reset[1, 3] = True
        for t in range(6):
            action = rng.uniform(-1, 1, (*shape, model.nu)).astype(np.float32)
            (s1, r1), (s3, r3) = [p.step(s, action) for p, s in zip((one, three), states)]
            np.testing.assert_array_equal(r3, r1)
            for a, b in zip(dataclasses.astuple(s3), dataclasses.astuple(s1), strict=True):
                np.testing.assert_array_equal(a, b)
            states = [s1, s3]
            if t == 2:  # two envs start again
                states = [
                    p.where(reset, p.init(qpos, qvel), s) for p, s in zip((one, three), states)
                ]
        assert np.abs(states[0].qpos - qpos).max() > 0.01  # the envs moved
        # On the pool's threads, never the caller's (which of them takes a block is the pool's
        # choice: a thread done with its block may take the next before another starts).
        assert stepped_on and all(n.startswith("physics") for n in stepped_on)
    finally:
        one.close()
        three.close()


def test_cpu_physics_refuses_state_it_does_not_load():
    walker = dmc.TASKS["walker-walk"].physics_model()
    with pytest.raises(ValueError, match="threads must be >= 1"):
        CpuPhysics(walker, None, n_sub_steps=1, action_repeat=1, threads=0)
    mocap = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body mocap="true"><geom size=".1"/></body></worldbody></mujoco>'
    )
    with pytest.raises(ValueError, match="state in mocap bodies"):
        CpuPhysics(mocap, None, n_sub_steps=1, action_repeat=1)


def test_solver_settings_reach_the_model():
    task = dmc.TASKS["finger-spin"]
    model = task.physics_model()
    assert model.opt.iterations == 200  # the XML's own
    phys = make_physics(
        "mjx",
        model,
        task.make_reward(model),
        n_sub_steps=2,
        action_repeat=2,
        solver=SolverSettings(iterations=3, ls_iterations=7),
    )
    assert (phys.mj_model.opt.iterations, phys.mj_model.opt.ls_iterations) == (3, 7)
    assert model.opt.iterations == 200  # the caller's model is not mutated
    keep = make_physics(
        "mjx",
        model,
        task.make_reward(model),
        n_sub_steps=2,
        action_repeat=2,
        solver=SolverSettings(iterations=None, ls_iterations=None),
    )
    assert keep.mj_model.opt.iterations == 200


def test_backend_names():
    with pytest.raises(ValueError, match="valid: mjx, cpu, auto"):
        make_physics("gpu", None, None, n_sub_steps=1, action_repeat=1)


# ---------------------------------------------------------------------------------------------
# The Env on the MJX backend (compiled on the CPU here) against the Env on CPU MuJoCo.


def test_env_mjx_backend_matches_cpu_and_resets_per_env():
    import jax
    import jax.numpy as jnp

    import envs

    def run(backend):
        with envs.make(
            "finger-spin",
            num_seeds=1,
            envs_per_seed=2,
            backend=backend,
            render=envs.RenderSettings(num_workers=1),
        ) as env:
            assert env.spec.backend == backend
            state, ts = env.reset(jax.random.key(5))
            out = [(np.asarray(state.physics.qpos), ts)]
            action = jnp.asarray([[[0.8, -0.5], [-0.3, 0.9]]], jnp.float32)
            for _ in range(3):
                state, ts = env.step(state, action)
                out.append((np.asarray(state.physics.qpos), ts))
            # Env 0 ends its episode now, env 1 does not (a kitchen-style terminal).
            state = dataclasses.replace(state, last=np.array([[True, False]]))
            state, ts = env.step(state, action)
            out.append((np.asarray(state.physics.qpos), ts))
        return out

    cpu, mjx_ = run("cpu"), run("mjx")
    for (q_cpu, ts_cpu), (q_mjx, ts_mjx) in zip(cpu, mjx_, strict=True):
        np.testing.assert_allclose(q_mjx, q_cpu, atol=2e-3)
        np.testing.assert_allclose(np.asarray(ts_mjx.reward), np.asarray(ts_cpu.reward), atol=1e-6)
        diff = np.abs(np.asarray(ts_mjx.frame, int) - np.asarray(ts_cpu.frame, int))
        assert diff.mean() < 1.0
    (q_before, _), (q_after, ts) = mjx_[-2], mjx_[-1]
    np.testing.assert_array_equal(np.asarray(ts.first), [[True, False]])
    assert float(ts.reward[0, 0]) == 0.0
    assert not np.allclose(q_after[0, 0], q_before[0, 0])  # env 0 restarted
    obs = np.asarray(ts.obs)
    np.testing.assert_array_equal(obs[0, 0, ..., 0:3], obs[0, 0, ..., 6:9])
    assert not np.array_equal(obs[0, 1, ..., 0:3], obs[0, 1, ..., 6:9])  # env 1 kept stacking


def test_mujoco_warnings_go_to_the_log_not_a_file(tmp_path, monkeypatch, caplog):
    """envs routes MuJoCo's warnings to Python's logging: no MUJOCO_LOG.TXT in the working
    directory."""
    import mujoco

    import envs  # noqa: F401  (installs the handler)

    monkeypatch.chdir(tmp_path)
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body><joint/><geom size="1"/></body></worldbody></mujoco>'
    )
    data = mujoco.MjData(model)
    data.qpos[:] = float("nan")
    mujoco.mj_step(model, data)
    assert "Nan, Inf or huge value in QPOS" in caplog.text
    assert not list(tmp_path.iterdir())


def test_the_gil_benchmark_steps_at_the_interval_while_the_load_runs():
    """benchmarks/gil.py: the physics steps on a thread of its own at the interval asked for,
    while the calling thread runs its load until the last step; the interval comes back."""
    from benchmarks import gil

    class Physics:
        def __init__(self):
            self.seen = []

        def step(self, state, action):
            self.seen.append((sys.getswitchinterval(), threading.current_thread().name))
            return state + action, None

    before = sys.getswitchinterval()
    for load in (None, gil._python, gil._dispatch):
        phys = Physics()
        ms = gil.step_ms(phys, 0, [1, 2], 5, load, 2e-4)
        assert len(phys.seen) == 5 and ms >= 0
        assert all(interval == pytest.approx(2e-4) for interval, _ in phys.seen)
        assert threading.current_thread().name not in {name for _, name in phys.seen}
        assert sys.getswitchinterval() == before
