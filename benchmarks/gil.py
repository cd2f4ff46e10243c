"""CPU physics on the env's thread while the training loop's thread works: the GIL's toll.

    python -m benchmarks.gil --task kitchen-kettle --seeds 3 --envs 16 --threads 1 \
        --intervals 5 1 0.1 --out benchmarks/results/gil_kitchen_cpu.json

The training loop steps CPU MuJoCo on the env's thread (and its `--threads` physics threads)
while its own thread dispatches updates. Each env's step takes and releases the GIL several times
(loading its state, MuJoCo's calls, the controller, the reward's views); a thread that wants the
GIL back waits until the holder lets go, by default up to Python's 5 ms switch interval. This
times one agent step of S x E envs there, median of `--steps`, while the calling thread is idle,
runs Python ("python"), dispatches small jitted calls 8 at a time ("dispatch"), or dispatches
one seed's learner update 8 at a time as the loop does between two env steps ("update", of
`--update-method`; for GPU machines: on a CPU the updates themselves take the cores), at each
switch interval of `--intervals` (ms). Writes JSON (--out).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from benchmarks.common import save_json
from benchmarks.envs import _action_repeat, _task
from envs import dmc
from envs.physics import CpuPhysics


def _python(stop: threading.Event) -> None:
    x = 0
    while not stop.is_set():
        for i in range(1000):
            x += i * i


def _dispatch(stop: threading.Event) -> None:
    f = jax.jit(lambda x: x * 2.0 + 1.0)
    x = jnp.ones((64, 64))
    while not stop.is_set():
        for _ in range(8):
            x = f(x)
        x.block_until_ready()


def _update(method: str = "drqv2", batch: int = 512):
    """A load that dispatches one seed's learner update (bf16, the default conv stacks) 8 at a
    time, as the loop does between two env steps; compiled here, before any timing."""
    from benchmarks.update import update_setup

    step, states, batches, hp = update_setup(
        method, 1, batch, "bfloat16", "hybrid", conv_stack="auto"
    )
    held = {"states": states, "round": 0}

    def dispatch_8():
        keys = jax.random.split(jax.random.key(held["round"]), 8)
        held["round"] += 1
        for k in keys:
            held["states"], metrics = step(held["states"], batches, k[None], hp)
        jax.block_until_ready(metrics)

    dispatch_8()

    def load(stop: threading.Event) -> None:
        while not stop.is_set():
            dispatch_8()

    return load


LOADS = {"idle": None, "python": _python, "dispatch": _dispatch}  # and "update", built when asked


def step_ms(phys: CpuPhysics, state, actions, steps: int, load, interval_s: float) -> float:
    """Median ms per agent step of `phys` on a thread of its own while this thread runs `load`
    (None: waits), Python's switch interval set to `interval_s` meanwhile."""
    times, before = [], sys.getswitchinterval()

    def stepping():
        s = state
        for i in range(steps):
            t = time.perf_counter()
            s, _ = phys.step(s, actions[i % len(actions)])
            times.append(time.perf_counter() - t)

    sys.setswitchinterval(interval_s)
    stop = threading.Event()
    worker = threading.Thread(target=stepping)
    try:
        worker.start()
        if load is None:
            worker.join()
        else:
            waiter = threading.Thread(target=lambda: (worker.join(), stop.set()))
            waiter.start()
            load(stop)
            waiter.join()
    finally:
        sys.setswitchinterval(before)
    return float(np.median(times) * 1e3)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="kitchen-kettle", choices=envs.names())
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--threads", type=int, nargs="+", default=[1], help="CPU MuJoCo's threads")
    p.add_argument(
        "--loads", nargs="+", default=["idle", "python", "dispatch"], choices=[*LOADS, "update"]
    )
    p.add_argument("--update-method", default="drqv2", help="the update the load 'update' runs")
    p.add_argument("--intervals", type=float, nargs="+", default=[5.0, 1.0, 0.1], help="ms")
    p.add_argument("--steps", type=int, default=6)
    p.add_argument("--out", default="")
    args = p.parse_args(argv)

    task = _task(args.task)
    model = task.physics_model()
    shape = (args.seeds, args.envs)
    qpos, qvel = dmc.episode_starts(task, model, args.seeds * args.envs)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, shape + (model.nu,)) for _ in range(4)]
    rows = []
    print(f"{args.task}, {args.seeds} x {args.envs} envs: ms per agent step")
    print("threads | calling thread | switch interval ms | ms per step")
    for threads in args.threads:
        phys = CpuPhysics(
            model,
            task.make_reward(model),
            n_sub_steps=task.n_sub_steps(model),
            action_repeat=_action_repeat(task.name),
            control=task.make_control(model),
            threads=threads,
        )
        try:
            state = phys.init(qpos.reshape(shape + (-1,)), qvel.reshape(shape + (-1,)))
            phys.step(state, actions[0])  # compiles the reward
            for load in args.loads:
                work = _update(args.update_method) if load == "update" else LOADS[load]
                for interval in args.intervals:
                    ms = step_ms(phys, state, actions, args.steps, work, interval / 1e3)
                    rows.append(
                        dict(threads=threads, load=load, interval_ms=interval, ms_per_step=ms)
                    )
                    print(f"{threads:7d} | {load:14s} | {interval:18g} | {ms:11.1f}", flush=True)
        finally:
            phys.close()
    save_json(dict(task=args.task, seeds=args.seeds, envs=args.envs, rows=rows), args.out)


if __name__ == "__main__":
    main()
