"""The graphics load of an evaluation, alone: a render pool drawing a batch at a fixed pace.

    python -m benchmarks.render_load --batch 30 --interval-ms 40 --seconds 120 --workers 8

An evaluation of 10 episodes x 3 seeds draws 30 observations (RGB + labels, dm_control's
picture) per step, about every 40 ms on an H100. Run beside a training run without evaluation
(`bash benchmarks/train_device.sh gpushare`), this asks whether an evaluation slows training
through the GPU its render workers draw on (EGL contexts time-sliced with the training's CUDA
work) rather than through CPU cores or the training process's threads. Prints and writes the
batches drawn and their mean time (JSON: --out).
"""

from __future__ import annotations

import argparse
import functools
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from benchmarks.common import save_json  # noqa: E402
from benchmarks.render import random_states  # noqa: E402
from envs import dmc  # noqa: E402
from envs.render import RenderPool, RenderSettings  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="walker-walk", choices=sorted(dmc.TASKS))
    p.add_argument("--batch", type=int, default=30)
    p.add_argument("--interval-ms", type=float, default=40.0)
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--workers", type=int, default=8)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    task = dmc.TASKS[args.task]
    model = task.render_model()
    qpos = random_states(model, args.batch)
    with RenderPool(
        functools.partial(dmc.render_model_fn, task.name),
        camera=task.camera,
        agent_geom_ids=task.agent_geom_ids(model),
        floor_geom_ids=task.floor_geom_ids(model),
        settings=RenderSettings(num_workers=args.workers),
    ) as pool:
        pool.render(qpos)  # workers started and warm
        times = []
        end = time.perf_counter() + args.seconds
        while time.perf_counter() < end:
            t0 = time.perf_counter()
            pool.render(qpos)
            times.append(time.perf_counter() - t0)
            time.sleep(max(0.0, args.interval_ms / 1e3 - times[-1]))
    result = dict(
        vars(args),
        batches=len(times),
        mean_ms=float(np.mean(times) * 1e3),
        p90_ms=float(np.percentile(times, 90) * 1e3),
        observations_per_s=len(times) * args.batch / args.seconds,
    )
    print(
        f"{len(times)} batches of {args.batch} in {args.seconds:.0f} s: "
        f"{result['mean_ms']:.1f} ms each (p90 {result['p90_ms']:.1f}), "
        f"{result['observations_per_s']:.0f} observations/s"
    )
    save_json(result, args.out, "benchmarks/results/render_load.json")


if __name__ == "__main__":
    main()
