"""Kitchen exploration: how often an untrained agent's actions move the light switch or the kettle.

Steps the Franka Kitchen (envs/kitchen.py) on CPU MuJoCo through the env's own CPU backend
(`envs.physics.CpuPhysics` with the task's model, joint-velocity control and reward) from the
task's fixed start, for whole 280-step episodes, without rendering. Every episode runs to its
end (a success does not stop it here), so one set of rollouts serves both tasks: scene, start
and actions are the same, only the goal differs. Action modes:
- `uniform`: uniform actions in [-1, 1]^9, what the agent does for its first
  `agent.explore_steps` (2000) agent steps per seed, counted over all of a seed's envs;
- `noise`: the policy's exploration around a zero mean: clamp(N(0, std^2), -1 + 1e-6, 1 - 1e-6)
  per dimension (`dear_jax.update.sample_action`, which acting calls without a noise clip; the
  `stddev_clip` of 0.3 applies to the critic's target only);
- `actor`: the same noise around the mean of a freshly initialised actor (`dear_jax.update.init`
  of `--actor-seeds` seeds, on the task's observation at the episode start, rendered at the
  training's "dm_control" quality); each episode keeps one seed's mean, cycling over the seeds.
  `--actor-trajectory` steps of uniform actions measure how much that mean changes as the robot
  moves (`actor_mean.drift`): the untrained mean is nearly constant, a drift over an episode;
- `zero`: the zero action (one episode: it is deterministic), the controller alone;
- `ou`: temporally correlated noise around a zero mean, a_t = clamp(n_t) with
  n_t = rho n_{t-1} + sqrt(1 - rho^2) std eps_t (`--rho`; n_0 ~ N(0, std^2)), as a trained
  actor's slowly changing mean would correlate actions: not what the agent does (a counterfactual
  for how far correlated actions carry the hand against the controller's creep).
`--std` is the exploration std (1.0 after the uniform phase; 0.91 at 47.6k agent steps per seed
on the 500k-step schedule). `--repeat` k holds each sampled action for k agent steps (SEAR's
training config, from which DEAR's code derives, defaults to action repeat 2; an episode stays
280 steps of 0.08 s here). `--robot-gravcomp` is a counterfactual, not the task: MuJoCo's
gravity compensation on the robot's bodies removes the creep of the velocity controller (each
agent step's target is the current, gravity-sagged position plus the commanded motion, so under
a zero action the arm sinks; D4RL's and gymnasium-robotics' controllers do the same).

Per episode and task: success (the task's reward 1 at some step: its qpos slice within 0.3 of
its goal), the first such step and the minimum goal distance over the episode; the largest
displacement from the start of the switch hinge (qpos 17), the light slide (qpos 18), the
kettle's position (qpos 23-25) and the kettle's largest tilt; the closest the hand's
`end_effector` site (between the fingertips) came to the switch (`light_site`) and to the kettle
(`kettle_site`), and the largest rise and drop of its height. Summarised per mode and task:
success rate, episodes per success, the fraction of episodes that moved the object by more than
each `--thresholds` value, and quantiles of the rest.

Timing: CPU MuJoCo ms per agent step (40 physics steps), one env on one thread stepped with
`mj_step` and the task's control, and per env through `CpuPhysics` with 16 envs on one thread
(its Python overhead included); each mode also stores its rollouts' physics time per env step.

    MUJOCO_GL=egl python -m benchmarks.kitchen_exploration --episodes 500 \
        --out benchmarks/results/kitchen_exploration_cpu.json
    python -m benchmarks.kitchen_exploration --modes noise uniform --episodes 200 \
        --robot-gravcomp --out benchmarks/results/kitchen_exploration_gravcomp_cpu.json
    python -m benchmarks.kitchen_exploration --modes noise --episodes 200 --repeat 2 \
        --out benchmarks/results/kitchen_exploration_repeat2_cpu.json
    python -m benchmarks.kitchen_exploration --modes ou --episodes 200 --rho 0.9 \
        --out benchmarks/results/kitchen_exploration_ou_cpu.json
    python -m benchmarks.kitchen_exploration --modes uniform --episodes 200 --repeat 10 \
        --out benchmarks/results/kitchen_exploration_repeat10_cpu.json
    python -m benchmarks.kitchen_exploration --modes noise --episodes 200 --repeat K \
        --out benchmarks/results/kitchen_exploration_noise_repeatK_cpu.json  # K = 5 10 20 40

`--modes noise --repeat K` is what training does with `agent.noise_hold` K at a zero mean.
"""

from __future__ import annotations

import argparse
import copy
import functools
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.common import save_json  # noqa: E402
from envs import kitchen  # noqa: E402
from envs.physics import CpuPhysics  # noqa: E402

MODES = ("uniform", "noise", "actor", "zero", "ou")
TASKS = ("kitchen-light", "kitchen-kettle")
SWITCH, SLIDE, KETTLE_POS, KETTLE_QUAT = 17, 18, slice(23, 26), slice(26, 30)
HAND_SITE = "end_effector"
TARGET_SITES = {"kitchen-light": "light_site", "kitchen-kettle": "kettle_site"}


# --------------------------------------------------------------------------------------------
# The untrained actor's mean.


def actor_means(num_seeds: int, trajectory: int, seed: int) -> dict:
    """Means [num_seeds, 9] of freshly initialised actors on the start observation, and how they
    change over `trajectory` uniform-action steps of one env (rendered, as the training sees it)."""
    import envs
    from configs.kitchen import make as kitchen_config
    from dear_jax import experiment, update
    from envs.render import RenderSettings

    config = kitchen_config("light", "dear")
    cfg = experiment.agent_config(config, action_dim=kitchen.NUM_ROBOT_JOINTS)
    states = update.init_seeds(cfg, jax.random.split(jax.random.key(seed), num_seeds))
    hp = update.HParams()
    render = RenderSettings(**{**config.env.render.to_dict(), "num_workers": 1})
    rng = np.random.default_rng(seed)
    obs = []
    with envs.make(
        "kitchen-light", num_seeds=1, envs_per_seed=1, backend="cpu", render=render
    ) as env:
        state, ts = env.reset(jax.random.key(seed))
        obs.append(np.asarray(ts.obs)[0, 0])
        for _ in range(trajectory):
            action = rng.uniform(-1, 1, (1, 1, kitchen.NUM_ROBOT_JOINTS)).astype(np.float32)
            state, ts = env.step(state, jnp.asarray(action))
            obs.append(np.asarray(ts.obs)[0, 0])
    obs = jnp.asarray(np.stack(obs))  # [T+1, 84, 84, 9]

    def mean_of(agent):
        return update.act(cfg, agent, obs, jax.random.key(0), hp, explore=False)[0]

    means = np.asarray(jax.jit(jax.vmap(mean_of))(states))  # [K, T+1, 9]
    start = means[:, 0]
    drift = np.abs(means - start[:, None]).max(axis=(1, 2))  # per seed, over the trajectory
    return {
        "seeds": num_seeds,
        "trajectory_steps": trajectory,
        "start": start.round(5).tolist(),
        "abs_mean": float(np.abs(start).mean()),
        "abs_max": float(np.abs(start).max()),
        "norm_mean": float(np.linalg.norm(start, axis=-1).mean()),
        "drift": drift.round(5).tolist(),  # max |mean(t) - mean(0)| per seed
    }


# --------------------------------------------------------------------------------------------
# Rollouts.


@functools.lru_cache(maxsize=1)
def _gravcomp_model() -> mujoco.MjModel:
    """The physics model with gravity compensation on every robot body (a counterfactual)."""
    robot = kitchen.robot_body_ids(kitchen.TASKS["kitchen-light"].physics_model())
    names = {kitchen.TASKS["kitchen-light"].physics_model().body(b).name for b in robot}
    load = kitchen.load_spec

    def load_with_gravcomp():
        spec = load()
        bodies = list(spec.bodies)
        for body in bodies:
            if body.name in names:
                body.gravcomp = 1.0
        # The pedestal is unnamed: it has no joint below the world and carries no load.
        return spec

    kitchen.load_spec = load_with_gravcomp
    try:
        model = kitchen.build_physics_model()
    finally:
        kitchen.load_spec = load
    return model


def _physics(threads: int = 1, gravcomp: bool = False):
    task = kitchen.TASKS["kitchen-light"]
    model = copy.copy(_gravcomp_model()) if gravcomp else task.physics_model()
    phys = CpuPhysics(
        model,
        task.make_reward(model),
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=1,
        control=task.make_control(model),
        threads=threads,
    )
    return task, model, phys


def _start(task, model, n):
    data = mujoco.MjData(model)
    task.init_episode(model, data, None)
    qpos = np.broadcast_to(data.qpos, (1, n, model.nq)).copy()
    qvel = np.broadcast_to(data.qvel, (1, n, model.nv)).copy()
    return qpos, qvel


def _tilt(quat: np.ndarray) -> np.ndarray:
    """Angle (rad) between the kettle's up axis and the world's; quat [..., 4] w-first."""
    w, x, y, z = np.moveaxis(quat / np.linalg.norm(quat, axis=-1, keepdims=True), -1, 0)
    up_z = 1 - 2 * (x * x + y * y)  # z component of the body z axis
    return np.arccos(np.clip(up_z, -1, 1))


def rollout(
    mode: str,
    n: int,
    rng: np.random.Generator,
    means: np.ndarray | None,
    std: float,
    first_episode: int,
    repeat: int = 1,
    gravcomp: bool = False,
    rho: float = 0.9,
) -> dict:
    """`n` episodes of `mode` in one batch of n envs, each sampled action held for `repeat`
    steps; per-episode records [n]."""
    from dear_jax.update import sample_action

    task, model, phys = _physics(gravcomp=gravcomp)
    qpos0, qvel0 = _start(task, model, n)
    state = phys.init(qpos0, qvel0)
    start = qpos0[0]
    data = mujoco.MjData(model)
    hand, targets = model.site(HAND_SITE).id, {k: model.site(s).id for k, s in TARGET_SITES.items()}
    goal = {name: kitchen.TASKS[name] for name in TASKS}
    mu = np.zeros((n, model.nu), np.float32)
    if mode == "actor":
        mu = means[(first_episode + np.arange(n)) % len(means)].astype(np.float32)
    sample = jax.jit(sample_action)
    key = jax.random.key(int(rng.integers(2**31)))

    steps = kitchen.EPISODE_STEPS
    first_success = {name: np.full(n, -1) for name in TASKS}
    min_dist = {name: np.full(n, np.inf) for name in TASKS}
    near = {name: np.full(n, np.inf) for name in TASKS}
    data.qpos[:] = start[0]
    mujoco.mj_kinematics(model, data)
    hand_z0 = float(data.site_xpos[hand][2])
    rise, drop = np.zeros(n), np.zeros(n)
    moved = {
        "switch": np.zeros(n),
        "slide": np.zeros(n),
        "kettle": np.zeros(n),
        "tilt": np.zeros(n),
    }
    wall = 0.0
    ou = rng.normal(0.0, std, (1, n, model.nu)) if mode == "ou" else None
    for t in range(steps):
        if t % repeat:
            pass  # hold the last action
        elif mode == "ou":
            if t:
                ou = rho * ou + np.sqrt(1 - rho**2) * std * rng.normal(size=ou.shape)
            action = np.clip(ou, -1 + 1e-6, 1 - 1e-6).astype(np.float32)
        elif mode == "uniform":
            action = rng.uniform(-1, 1, (1, n, model.nu)).astype(np.float32)
        elif mode == "zero":
            action = np.zeros((1, n, model.nu), np.float32)
        else:
            key, k = jax.random.split(key)
            action = np.asarray(sample(jnp.asarray(mu), std, k))[None]
        t0 = time.perf_counter()
        state, reward = phys.step(state, action)
        wall += time.perf_counter() - t0
        q = phys.qpos(state)[0]  # [n, nq]
        for name in TASKS:
            d = goal[name].goal_distance(q)
            hit = (d < kitchen.SUCCESS_THRESHOLD) & (first_success[name] < 0)
            first_success[name][hit] = t + 1
            min_dist[name] = np.minimum(min_dist[name], d)
        # The backend's own reward is the light's: it must agree with the goal distance.
        light_now = goal["kitchen-light"].goal_distance(q) < kitchen.SUCCESS_THRESHOLD
        if not np.array_equal(reward[0] > 0, light_now):
            raise AssertionError(
                f"step {t}: backend reward disagrees with the light's goal distance"
            )
        moved["switch"] = np.maximum(moved["switch"], np.abs(q[:, SWITCH] - start[:, SWITCH]))
        moved["slide"] = np.maximum(moved["slide"], np.abs(q[:, SLIDE] - start[:, SLIDE]))
        moved["kettle"] = np.maximum(
            moved["kettle"], np.linalg.norm(q[:, KETTLE_POS] - start[:, KETTLE_POS], axis=-1)
        )
        moved["tilt"] = np.maximum(moved["tilt"], _tilt(q[:, KETTLE_QUAT]))
        for e in range(n):
            data.qpos[:] = q[e]
            mujoco.mj_kinematics(model, data)
            for name, site in targets.items():
                gap = np.linalg.norm(data.site_xpos[hand] - data.site_xpos[site])
                near[name][e] = min(near[name][e], gap)
            dz = data.site_xpos[hand][2] - hand_z0
            rise[e], drop[e] = max(rise[e], dz), min(drop[e], dz)
    if not np.isfinite(phys.qpos(state)).all():
        raise FloatingPointError(f"{mode}: non-finite qpos")
    phys.close()
    return {
        "first_success": first_success,
        "min_dist": min_dist,
        "hand_to_target": near,
        "moved": moved,
        "hand_height": {"rise": rise, "drop": drop},
        "physics_s": wall,
        "env_steps": n * steps,
    }


def _quantiles(x: np.ndarray) -> dict:
    qs = (0.0, 0.1, 0.5, 0.9, 0.99, 1.0)
    return {f"q{int(q * 100)}": round(float(np.quantile(x, q)), 4) for q in qs}


def summarise(records: dict, thresholds: list[float]) -> dict:
    out = {}
    n = len(records["moved"]["switch"])
    for name in TASKS:
        first = records["first_success"][name]
        wins = first > 0
        obj = records["moved"]["switch"] if name == "kitchen-light" else records["moved"]["kettle"]
        unit = "rad" if name == "kitchen-light" else "m"
        out[name] = {
            "episodes": n,
            "successes": int(wins.sum()),
            "success_rate": float(wins.mean()),
            "episodes_per_success": float(n / wins.sum()) if wins.any() else None,
            "first_success_episode": int(np.flatnonzero(wins)[0]) + 1 if wins.any() else None,
            "first_success_step": _quantiles(first[wins]) if wins.any() else None,
            "moved_object": f"max |displacement| ({unit}) of "
            + (
                "the switch hinge, qpos 17" if name == "kitchen-light" else "the kettle, qpos 23-25"
            ),
            "moved_fraction": {f"{th:g}": float((obj > th).mean()) for th in thresholds},
            "moved_quantiles": _quantiles(obj),
            "min_goal_distance": _quantiles(records["min_dist"][name]),
            "min_hand_to_target_m": _quantiles(records["hand_to_target"][name]),
        }
    out["hand_height_m"] = {
        "note": "largest rise / drop of the end_effector site's height from the start over the episode",
        "rise": _quantiles(records["hand_height"]["rise"]),
        "drop": _quantiles(records["hand_height"]["drop"]),
    }
    out["kitchen-light"]["slide_moved_quantiles_m"] = _quantiles(records["moved"]["slide"])
    out["kitchen-kettle"]["tilt_quantiles_rad"] = _quantiles(records["moved"]["tilt"])
    return out


def _merge(parts: list[dict]) -> dict:
    cat = lambda key: {k: np.concatenate([p[key][k] for p in parts]) for k in parts[0][key]}  # noqa: E731
    return {
        key: cat(key)
        for key in ("first_success", "min_dist", "hand_to_target", "moved", "hand_height")
    } | {
        "physics_s": sum(p["physics_s"] for p in parts),
        "env_steps": sum(p["env_steps"] for p in parts),
    }


# --------------------------------------------------------------------------------------------
# Timing.


def time_physics(steps: int, batch: int) -> dict:
    """ms per agent step: mj_step x 40 with the task's control (one env), and CpuPhysics.step
    over `batch` envs on one thread, per env. Uniform random actions from the start."""
    task, model, phys = _physics()
    control = task.make_control(model)
    data = mujoco.MjData(model)
    task.init_episode(model, data, None)
    rng = np.random.default_rng(0)
    n_sub = task.n_sub_steps(model)
    t0 = time.perf_counter()
    for _ in range(steps):
        data.ctrl[:] = control(data.qpos, rng.uniform(-1, 1, model.nu), np)
        mujoco.mj_step(model, data, n_sub)
    raw = (time.perf_counter() - t0) / steps * 1e3

    qpos, qvel = _start(task, model, batch)
    state = phys.init(qpos, qvel)
    state, _ = phys.step(state, rng.uniform(-1, 1, (1, batch, model.nu)))  # compiles the reward
    calls = max(1, steps // batch)
    t0 = time.perf_counter()
    for _ in range(calls):
        state, _ = phys.step(state, rng.uniform(-1, 1, (1, batch, model.nu)))
    batched = (time.perf_counter() - t0) / (calls * batch) * 1e3
    phys.close()
    return {
        "mj_step_ms_per_agent_step": round(raw, 3),
        "physics_steps_per_agent_step": n_sub,
        "cpu_physics_batch": batch,
        "cpu_physics_ms_per_env_step": round(batched, 3),
        "steps": steps,
        "solver": {
            "iterations": int(model.opt.iterations),
            "ls_iterations": int(model.opt.ls_iterations),
        },
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--episodes", type=int, default=500, help="per mode")
    p.add_argument("--batch", type=int, default=50, help="episodes stepped together (one thread)")
    p.add_argument("--repeat", type=int, default=1, help="agent steps each action is held")
    p.add_argument("--robot-gravcomp", action="store_true", help="counterfactual: no creep")
    p.add_argument("--std", type=float, default=1.0, help="exploration std (noise, actor, ou)")
    p.add_argument("--rho", type=float, default=0.9, help="ou: correlation of successive steps")
    p.add_argument("--actor-seeds", type=int, default=16)
    p.add_argument("--actor-trajectory", type=int, default=60)
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.05, 0.15, 0.39])
    p.add_argument("--timing-steps", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--label", default="", help="free text stored with the results")
    p.add_argument("--out", default="")
    args = p.parse_args(argv)

    result = {"label": args.label, "args": vars(args), "cpu_count": os.cpu_count()}
    result["timing"] = time_physics(args.timing_steps, min(args.batch, 16))
    print("timing", result["timing"], flush=True)
    means = None
    if "actor" in args.modes:
        result["actor_mean"] = actor_means(args.actor_seeds, args.actor_trajectory, args.seed)
        means = np.asarray(result["actor_mean"]["start"])
        m = result["actor_mean"]
        print(
            f"actor mean |mu| {m['abs_mean']:.3f}, max {m['abs_max']:.3f}, drift {max(m['drift']):.3f}"
        )
    rng = np.random.default_rng(args.seed)
    result["modes"] = {}
    for mode in args.modes:
        parts, done = [], 0
        episodes = 1 if mode == "zero" else args.episodes
        while done < episodes:
            n = min(args.batch, episodes - done)
            parts.append(
                rollout(
                    mode, n, rng, means, args.std, done, args.repeat, args.robot_gravcomp, args.rho
                )
            )
            done += n
            light = sum(int((q["first_success"]["kitchen-light"] > 0).sum()) for q in parts)
            kettle = sum(int((q["first_success"]["kitchen-kettle"] > 0).sum()) for q in parts)
            print(f"{mode}: {done} episodes, successes light {light}, kettle {kettle}", flush=True)
        records = _merge(parts)
        summary = summarise(records, args.thresholds)
        summary["physics_ms_per_env_step"] = round(
            records["physics_s"] / records["env_steps"] * 1e3, 3
        )
        result["modes"][mode] = summary
        for name in TASKS:
            s = summary[name]
            line = f"{mode:8s} {name:15s} success {s['successes']}/{s['episodes']}"
            line += f", moved > {s['moved_fraction']}, median min goal distance "
            print(line + f"{s['min_goal_distance']['q50']}", flush=True)
    save_json(result, args.out)


if __name__ == "__main__":
    main()
