"""Environment benchmark: physics ms per agent step, render observations/s, whole env steps.

For `--seeds` S x E envs (E from `--envs`), on one task (walker-walk by default; the kitchen
tasks too, e.g. `--task kitchen-light`: action repeat 1, 40 physics steps per agent step):
- physics: MJX (or CPU MuJoCo) through one agent step (action repeat x substeps), timed per step
  including the qpos fetch to the host that rendering needs (what a training step pays), and
  also as a chain of dispatched steps with one sync at the end (pure device throughput);
- render: the render pool turning S*E states into RGB + labels (84x84), observations/s;
- env: `Env.step` end to end (physics + render + compositing + masks + frame stack).
Prints a table and writes JSON (`--out`) with the device and GL renderer names.

    python -m benchmarks.envs --what physics render env --out benchmarks/results/envs.json
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402
from benchmarks.common import save_json
from envs import dmc, kitchen  # noqa: E402
from envs.physics import SolverSettings, make_physics  # noqa: E402
from envs.render import RenderSettings  # noqa: E402
from envs.render_pool import RenderPool  # noqa: E402


def _task(name):
    return kitchen.TASKS[name] if name in kitchen.TASKS else dmc.TASKS[name]


def _action_repeat(name) -> int:
    return 1 if name in kitchen.TASKS else 2  # docs/method.md: kitchen 1, DMC 2


def bench_physics(task, backend, seeds, num_envs, solver, steps, threads=1):
    model = task.physics_model()
    phys = make_physics(
        backend,
        model,
        task.make_reward(model),
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=_action_repeat(task.name),
        solver=solver,
        control=task.make_control(model),
        threads=threads,
    )
    shape = (seeds, num_envs)
    qpos, qvel = dmc.episode_starts(task, model, seeds * num_envs)
    state = phys.init(qpos.reshape(shape + (-1,)), qvel.reshape(shape + (-1,)))
    rng = np.random.default_rng(0)
    actions = [jnp.asarray(rng.uniform(-1, 1, shape + (model.nu,)), jnp.float32) for _ in range(8)]
    t0 = time.perf_counter()
    state, reward = phys.step(state, actions[0])
    np.asarray(phys.qpos(state))
    compile_s = time.perf_counter() - t0
    for i in range(3):
        state, reward = phys.step(state, actions[i % 8])
    np.asarray(phys.qpos(state))
    # Per step with the host fetch of qpos (the render pool needs it every step).
    t0 = time.perf_counter()
    for i in range(steps):
        state, reward = phys.step(state, actions[i % 8])
        np.asarray(phys.qpos(state))
    synced_ms = (time.perf_counter() - t0) / steps * 1e3
    # Chained: dispatch all, sync once.
    t0 = time.perf_counter()
    for i in range(steps):
        state, reward = phys.step(state, actions[i % 8])
    np.asarray(phys.qpos(state))
    chained_ms = (time.perf_counter() - t0) / steps * 1e3
    finite = bool(np.isfinite(np.asarray(phys.qpos(state))).all())
    if hasattr(phys, "close"):
        phys.close()
    return dict(
        seeds=seeds,
        envs=num_envs,
        backend=phys.name,
        threads=getattr(phys, "threads", None),
        solver=dataclasses.asdict(solver),
        compile_s=round(compile_s, 2),
        ms_per_step=round(synced_ms, 3),
        ms_per_step_chained=round(chained_ms, 3),
        physics_steps_per_agent_step=phys.n_sub_steps * phys.action_repeat,
        finite=finite,
    )


def _rollout_poses(task, model, n, seed=1):
    """Realistic poses: episode starts advanced by a few random-action control steps."""
    rng = np.random.RandomState(seed)
    data = mujoco.MjData(model)
    poses = []
    for _ in range(n):
        dmc.episode_start(task, model, data, rng)
        data.ctrl[:] = rng.uniform(-1, 1, model.nu)
        mujoco.mj_step(model, data, int(rng.randint(0, 200)))
        poses.append(data.qpos.copy())
    return np.array(poses)


def bench_render(task, seeds, env_counts, workers, calls):
    model = task.render_model()
    settings = RenderSettings(num_workers=workers)
    poses = _rollout_poses(task, task.physics_model(), seeds * max(env_counts))
    rows = []
    with RenderPool(
        task.render_factory(),
        camera=task.camera,
        agent_geom_ids=task.agent_geom_ids(model),
        floor_geom_ids=task.floor_geom_ids(model),
        settings=settings,
    ) as pool:
        gl = pool.gl_info()[0]
        for num_envs in env_counts:
            batch = seeds * num_envs
            qpos = poses[:batch]
            pool.render(qpos)
            t0 = time.perf_counter()
            for _ in range(calls):
                rgb, labels = pool.render(qpos)
            dt = time.perf_counter() - t0
            agent_frac = float((labels == 2).mean())
            rows.append(
                dict(
                    seeds=seeds,
                    envs=num_envs,
                    batch=batch,
                    workers=pool.num_workers,
                    ms_per_call=round(dt / calls * 1e3, 3),
                    obs_per_s=round(batch * calls / dt, 1),
                    agent_pixel_fraction=round(agent_frac, 4),
                )
            )
    return rows, gl


def bench_env(task_name, backend, seeds, num_envs, solver, workers, steps, distraction):
    with envs.make(
        task_name,
        num_seeds=seeds,
        envs_per_seed=num_envs,
        backend=backend,
        distraction=distraction,
        render=RenderSettings(num_workers=workers),
        solver=solver,
    ) as env:
        shape = (seeds, num_envs, env.spec.action_dim)
        action = jnp.zeros(shape, jnp.float32)
        state, ts = env.reset(jax.random.key(0))
        for _ in range(3):
            state, ts = env.step(state, action)
        jax.block_until_ready(ts.obs)
        t0 = time.perf_counter()
        for _ in range(steps):
            state, ts = env.step(state, action)
        jax.block_until_ready(ts.obs)
        dt = time.perf_counter() - t0
    return dict(
        seeds=seeds,
        envs=num_envs,
        backend=env.spec.backend,
        distraction=distraction,
        workers=workers,
        ms_per_step=round(dt / steps * 1e3, 3),
        obs_per_s=round(seeds * num_envs * steps / dt, 1),
        frames_per_s=round(seeds * num_envs * steps * env.spec.action_repeat / dt, 1),
    )


def _table(title, rows, cols):
    print(f"\n{title}")
    print(" | ".join(f"{c:>12}" for c in cols))
    for r in rows:
        print(" | ".join(f"{str(r.get(c, '')):>12}" for c in cols))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="walker-walk", choices=envs.names())
    p.add_argument(
        "--what", nargs="+", default=["physics", "render"], choices=["physics", "render", "env"]
    )
    p.add_argument("--backend", default="auto", choices=["auto", "mjx", "cpu"])
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--envs", type=int, nargs="+", default=[1, 8, 32])
    p.add_argument("--iterations", type=int, default=SolverSettings.iterations)
    p.add_argument("--ls-iterations", type=int, default=SolverSettings.ls_iterations)
    p.add_argument("--unroll", type=int, default=SolverSettings.unroll)
    p.add_argument("--solver", default=None, choices=["newton", "cg"])
    p.add_argument("--no-euler-damping", action="store_true")
    p.add_argument("--workers", type=int, nargs="+", default=[0])
    p.add_argument("--steps", type=int, default=50)
    p.add_argument(
        "--physics-threads", type=int, nargs="+", default=[1], help="CPU MuJoCo's threads"
    )
    p.add_argument("--calls", type=int, default=50)
    p.add_argument("--distraction", default="none")
    p.add_argument("--label", default="", help="free text stored with the results")
    p.add_argument("--out", default="")
    args = p.parse_args(argv)

    task = _task(args.task)
    solver = SolverSettings(
        args.iterations,
        args.ls_iterations,
        args.unroll,
        solver=args.solver,
        euler_damping=False if args.no_euler_damping else None,
    )
    result = dict(
        task=args.task,
        label=args.label,
        device=str(jax.devices()[0].device_kind),
        jax_backend=jax.default_backend(),
        jax_version=jax.__version__,
        mujoco_version=mujoco.__version__,
        cpu_count=os.cpu_count(),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        physics=[],
        render=[],
        env=[],
    )

    def save():
        save_json(result, args.out)

    if "physics" in args.what:
        for n in args.envs:
            for threads in args.physics_threads:
                result["physics"].append(
                    bench_physics(task, args.backend, args.seeds, n, solver, args.steps, threads)
                )
                save()
        _table(
            f"physics {args.task} ({result['device']}, {args.label})",
            result["physics"],
            [
                "seeds",
                "envs",
                "threads",
                "compile_s",
                "ms_per_step",
                "ms_per_step_chained",
                "finite",
            ],
        )
    if "render" in args.what:
        for w in args.workers:
            rows, gl = bench_render(task, args.seeds, args.envs, w, args.calls)
            result["render"] += rows
            result["gl"] = gl
            save()
        _table(
            f"render RGB + labels {args.task} (GL: {result.get('gl')})",
            result["render"],
            ["seeds", "envs", "workers", "ms_per_call", "obs_per_s"],
        )
    if "env" in args.what:
        for w in args.workers:
            for n in args.envs:
                result["env"].append(
                    bench_env(
                        args.task,
                        args.backend,
                        args.seeds,
                        n,
                        solver,
                        w,
                        args.steps,
                        args.distraction,
                    )
                )
                save()
        _table(
            f"env.step {args.task}",
            result["env"],
            ["seeds", "envs", "workers", "ms_per_step", "obs_per_s", "frames_per_s"],
        )
    save()
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
