"""What one evaluation costs, stage by stage, and where its arrays should live.

    python -m benchmarks.evaluation --config configs/walker_drqv2_paper.py --steps 100 \
        --placements cpu:cpu accelerator:default accelerator:cpu --load

Builds the evaluation process's env and policy as `dear_jax.evaluator.build` does, in this
process (pinned to the upper half of the cores, as that process is), for each placement
POLICY:ENV (the policy on the accelerator or on XLA:CPU in float32; the env's array work, its
uploads, frame stack and compositing, on the process's default device or on XLA:CPU), and runs
`--reps` evaluations of `num_eval_episodes` episodes per seed, each `--steps` agent steps long.
Each stage is timed to its end: the policy, the physics, the render workers, the env's array
work (`post`), with `--video` the writing of each seed's mp4 (`video`; the run's evaluations
write them, `save_video`), and what is left (`other`: the evaluation loop's own array work and
Python, the videos' frames put side by side); all in ms per agent step, the episode start's
picture and the last policy call included, and the whole evaluation in seconds.

With `--load`, the evaluations run beside a training run of the same config without evaluation
in another process (`run.py`, CPU physics), started first and measured on: the evaluation
process's situation in a run. An evaluation's first rep compiles; the table shows
the fastest of the others. Prints a table; writes JSON (--out).
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

os.environ.setdefault("MUJOCO_GL", "egl")
# Beside the load's preallocated pool, as the evaluation process: only what it uses.
os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"

import jax  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.common import save_json  # noqa: E402
from dear_jax import evaluator, experiment, update  # noqa: E402
from dear_jax.config import load_config  # noqa: E402
from dear_jax.logger import format_table  # noqa: E402

STAGES = ("policy", "physics", "render", "post", "video")


class StageTimes:
    """Wraps callables so that each call is timed to its end (its arrays ready)."""

    def __init__(self):
        self.total = dict.fromkeys(STAGES, 0.0)

    def wrap(self, name, fn):
        def timed(*args, **kwargs):
            t = time.perf_counter()
            out = jax.block_until_ready(fn(*args, **kwargs))
            self.total[name] += time.perf_counter() - t
            return out

        return timed


def start_load(args, workdir: str) -> tuple[subprocess.Popen, list]:
    """A training run of the config without evaluation (after its first, of one episode per
    seed) in a process of its own, CPU physics; returns once it has logged three rows (the
    first compiles). `rows` goes on collecting its rows while the evaluations run. Its replay
    holds 100k transitions per seed: enough to sample from, and it fits beside the evaluations
    wherever the learning check's own does."""
    cmd = [
        sys.executable, "run.py", "--config", args.config, "--workdir", workdir,
        f"--config.seeds={args.seeds}", "--config.total_frames=100000000",
        "--config.eval_every_frames=1000000000", "--config.num_eval_episodes=1",
        "--config.eval_device=train", f"--config.log_every_frames={args.load_log_every}",
        "--config.checkpoint_every_frames=0", "--config.save_video=False",
        "--config.progress=False", "--config.env.backend=cpu", "--config.replay.disk=False",
        "--config.replay.capacity=100000",
    ]  # fmt: skip
    env = dict(os.environ, XLA_PYTHON_CLIENT_MEM_FRACTION="0.6")
    env.pop("XLA_PYTHON_CLIENT_PREALLOCATE")
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    rows, tail, ready = [], collections.deque(maxlen=20), threading.Event()

    def read():
        for line in proc.stdout:
            tail.append(line)
            if "frames/s in all" in line:
                rows.append(line.strip())
                if len(rows) >= 3:
                    ready.set()

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + args.load_start_s
    while not ready.wait(1.0) and proc.poll() is None and time.monotonic() < deadline:
        pass  # a load that fails (e.g. its replay does not fit) is reported at once
    if not ready.is_set() or proc.poll() is not None:
        code = proc.poll()
        proc.kill()
        proc.wait()
        why = f"exited with code {code}" if code is not None else f"ran {args.load_start_s} s"
        raise RuntimeError(
            f"the load {why} without logging 3 training rows: {' '.join(cmd)}\n" + "".join(tail)
        )
    return proc, rows


def measure(config, placement: str, threads: int, args) -> dict:
    policy_on, env_on = placement.split(":")
    env = None
    try:
        config.env.eval_physics_threads = threads
        # The eval env draws the true mask of its video's env only where videos are saved.
        config.save_video = config.save_video or args.video
        env, step, place = evaluator.build(config, policy_on=policy_on, env_on=env_on)
        acfg = experiment.agent_config(config, env.spec.action_dim)
        keys = jax.random.split(jax.random.key(0), env.shape[0])
        params = jax.jit(update.init_seeds, static_argnums=0)(acfg, keys).params
        policy = place(
            jax.tree.map(np.asarray, {k: params[k] for k in evaluator.POLICY_PARAMS if k in params})
        )
        physics_step, render, post = env.physics.step, env._pool.render, env._post
        reps = []
        for rep in range(args.reps):
            times = StageTimes()
            env.physics.step = times.wrap("physics", physics_step)
            env._pool.render = times.wrap("render", render)
            env._post = times.wrap("post", post)
            t = time.perf_counter()
            _, clips = evaluator.evaluate(
                env, times.wrap("policy", step), policy, jax.random.key(rep), video=args.video
            )
            if args.video:
                with tempfile.TemporaryDirectory() as folder:
                    write = times.wrap("video", evaluator.write_videos)
                    write(clips, [f"{folder}/{s}.mp4" for s in clips])
            wall = time.perf_counter() - t
            ms = {k: v / args.steps * 1e3 for k, v in times.total.items()}
            ms["other"] = wall / args.steps * 1e3 - sum(ms.values())
            reps.append({"wall_s": wall, "ms_per_step": ms})
        threads = getattr(env.physics, "threads", None)  # MJX physics has none
        return {"placement": placement, "physics_threads": threads, "reps": reps}
    finally:
        if env is not None:
            env.close()
        jax.config.update("jax_default_device", None)  # build's, for the next placement


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", default="configs/walker_drqv2_paper.py")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--steps", type=int, default=100, help="agent steps per episode")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument(
        "--placements",
        nargs="+",
        default=["accelerator:default", "accelerator:cpu", "cpu:cpu"],
        help="POLICY:ENV, POLICY in accelerator/cpu, ENV in default/cpu",
    )
    p.add_argument(
        "--physics-threads",
        type=int,
        nargs="+",
        default=[0],
        help="env.eval_physics_threads, each measured with each placement (0: the default)",
    )
    p.add_argument("--load", action="store_true", help="beside a training loop (another process)")
    p.add_argument(
        "--video",
        action="store_true",
        help="record and write each seed's video, as a run does (save_video)",
    )
    p.add_argument("--load-start-s", type=float, default=300.0)
    p.add_argument("--load-log-every", type=int, default=2500, help="the load's frames per row")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    for placement in args.placements:
        policy_on, _, env_on = placement.partition(":")
        if policy_on not in ("accelerator", "cpu") or env_on not in ("default", "cpu"):
            p.error(f"placement {placement!r}: POLICY in accelerator/cpu, ENV in default/cpu")
    config = load_config(args.config)  # e.g. configs/paper.py:walker,dear
    config.seeds = args.seeds
    config.env.episode_frames = args.steps * config.env.action_repeat
    cores = sorted(os.sched_getaffinity(0))
    # A SIGTERM (e.g. from `timeout`) unwinds through the `finally` below: the load stops too.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    workdir = tempfile.mkdtemp(prefix="evaluation_load_")
    load, rows, results = None, [], []

    def write():
        save_json(
            {
                "args": vars(args),
                "device": jax.devices()[0].device_kind,
                "episodes_per_seed": config.num_eval_episodes,
                "seeds": config.seeds,
                "load_rows": rows,
                "results": results,
            },
            args.out,
        )

    try:
        if args.load:
            load, rows = start_load(args, workdir)
        if len(cores) >= 4:  # as the evaluation process: the upper half of the cores
            os.sched_setaffinity(0, cores[len(cores) // 2 :])
        for placement in args.placements:
            for threads in args.physics_threads:
                results.append(measure(config, placement, threads, args))
                write()  # what is measured survives a later timeout
    finally:
        if load is not None:  # SIGTERM: the run stops its render workers
            load.terminate()
            try:
                load.wait(timeout=120)
            except subprocess.TimeoutExpired:
                load.kill()
        shutil.rmtree(workdir, ignore_errors=True)
    table = []
    for r in results:
        best = min(r["reps"][1:] or r["reps"], key=lambda x: x["wall_s"])
        r["best"] = best
        table.append(
            [r["placement"], r["physics_threads"], f"{best['wall_s']:.2f}"]
            + [f"{best['wall_s'] / args.steps * 1e3:.1f}"]
            + [f"{best['ms_per_step'][k]:.1f}" for k in (*STAGES, "other")]
        )
    print(
        f"\nOne evaluation step: {config.num_eval_episodes} episodes x {config.seeds} seeds, ms per step "
        f"({'beside a training loop' if load else 'alone'}; {jax.devices()[0].device_kind})"
    )
    print(
        format_table(
            ["policy:env", "physics threads", "evaluation s", "step", *STAGES, "other"], table
        )
    )
    write()


if __name__ == "__main__":
    main()
