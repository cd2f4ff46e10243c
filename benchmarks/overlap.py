"""Can physics and the seeds' updates share the GPU at once? One training iteration's GPU work.

    python -m benchmarks.overlap [--seeds 5] [--envs 8] [--batch 512] [--dtype bfloat16]

One iteration of the loop puts on the GPU one MJX physics step of S x E walker envs (~20 ms of
small, latency-bound kernels) and E/2 updates per seed (bandwidth-bound convolutions). XLA runs
a program's kernels on one stream unless a computation is annotated for another
(`jax.experimental.compute_on("gpu_stream:N")`). Timed here, each as one jitted program:
  physics        the physics step alone
  updates        the E/2 x S updates alone (seeds in a loop, one stream)
  updates/streams  the same with seed i on stream i % 2 + 1 (update.over_seeds "streams")
  sequential     physics, then the updates
  concurrent     physics on stream 1 while the updates run on the main stream
Prints a table of ms per iteration and writes JSON (benchmarks/results/overlap_<device>.json).
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import save_json
from benchmarks.envs import _initial_states
from benchmarks.update import update_setup
from dear_jax import update
from envs import dmc
from envs.physics import SolverSettings, make_physics


def _timed(fn, args, reps):
    out = fn(*args)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn(*args)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / reps * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--dtype", default="bfloat16", choices=["float32", "bfloat16"])
    parser.add_argument("--method", default="dear", choices=update.METHODS)
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--only", nargs="*", default=None, help="names of the programs to time")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    task = dmc.TASKS["walker-walk"]
    model = task.physics_model()
    phys = make_physics(
        "mjx",
        model,
        task.make_reward(model),
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=2,
        solver=SolverSettings(),
    )
    shape = (args.seeds, args.envs)
    qpos, qvel = _initial_states(task, model, args.seeds * args.envs)
    state = phys.init(qpos.reshape(shape + (-1,)), qvel.reshape(shape + (-1,)))
    action = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, shape + (model.nu,)), jnp.float32)

    n = args.envs // 2
    _, agents, batches, hp = update_setup(args.method, args.seeds, args.batch, args.dtype, "loop")
    keys = jax.random.split(jax.random.key(2), (n, args.seeds))

    def updates(agents, keys, how="loop"):
        step = update.over_seeds(functools.partial(update.update, cfg=_cfg(args)), how)

        def body(agents, k):
            agents, metrics = step(agents, batches, k, hp)
            return agents, metrics["loss"]

        return jax.lax.scan(body, agents, keys)

    physics = phys.step_fn

    def sequential(state, action, agents, keys):
        return physics(state, action), updates(agents, keys)

    def concurrent(state, action, agents, keys):
        return update.on_gpu_stream(physics, 1)(state, action), updates(agents, keys)

    programs = {
        "physics": (jax.jit(physics), (state, action)),
        "updates": (jax.jit(updates), (agents, keys)),
        "updates/streams": (jax.jit(functools.partial(updates, how="streams")), (agents, keys)),
        "sequential": (jax.jit(sequential), (state, action, agents, keys)),
        "concurrent": (jax.jit(concurrent), (state, action, agents, keys)),
    }
    rows = []
    for name, (fn, fn_args) in programs.items():
        if args.only and name not in args.only:
            continue
        t0 = time.perf_counter()
        try:
            ms = _timed(fn, fn_args, args.reps)
        except Exception as e:  # noqa: BLE001 - an unsupported annotation is a result too
            rows.append(dict(program=name, error=f"{type(e).__name__}: {e}"[:300]))
            print(f"{name}: failed: {rows[-1]['error']}")
            continue
        rows.append(dict(program=name, ms=ms, compile_and_run_s=time.perf_counter() - t0))
        print(f"{name}: {ms:.2f} ms per iteration")
    device = jax.devices()[0].device_kind
    print(
        f"\n{args.seeds} seeds x {args.envs} envs, {n} updates per seed per iteration, batch "
        f"{args.batch}, {args.dtype}, {device}\n| program | ms per iteration |\n|---|---:|"
    )
    for r in rows:
        print(
            f"| {r['program']} | {r['ms']:.2f} |" if "ms" in r else f"| {r['program']} | failed |"
        )
    save_json(
        dict(device=device, jax=jax.__version__, args=vars(args), rows=rows),
        args.out,
        f"benchmarks/results/overlap_{jax.devices()[0].platform}.json",
    )


def _cfg(args) -> update.AgentConfig:
    return update.AgentConfig(action_dim=6, method=args.method, compute_dtype=args.dtype)


if __name__ == "__main__":
    main()
