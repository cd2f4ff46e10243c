"""Render pool throughput: observations (RGB + pixel labels) per second vs workers and tiling.

    python -m benchmarks.render --workers 1 4 8 16 --tiles 1 64 --out benchmarks/results/render.json

One observation = one 84x84 RGB frame plus its label image, delivered to the caller as numpy
arrays (the pool's whole path: pickled qpos to the workers, kinematics, drawing, readback,
labels, shared memory, copy out). States are random walker poses. Prints a table and writes JSON
with the GL renderer string, so a run on Mesa llvmpipe cannot pass for a GPU run.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import platform
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from benchmarks.common import save_json
from envs import dmc  # noqa: E402
from envs.render import RenderPool, RenderSettings  # noqa: E402


def measure(task, workers, tiles, batch, calls, shadows):
    model = task.render_model()
    settings = RenderSettings(
        num_workers=workers, tiles_per_sheet=tiles, shadows=shadows, reflections=shadows
    )
    rng = np.random.default_rng(0)
    qpos = np.tile(model.qpos0, (batch, 1)) + rng.normal(0, 0.3, (batch, model.nq))
    t0 = time.perf_counter()
    with RenderPool(
        functools.partial(dmc.render_model_fn, task.name),
        camera=task.camera,
        agent_geom_ids=task.agent_geom_ids(model),
        floor_geom_ids=task.floor_geom_ids(model),
        settings=settings,
    ) as pool:
        start_s = time.perf_counter() - t0
        info = pool.gl_info()[0]
        pool.render(qpos)  # warm-up: shared memory, GL state
        t0 = time.perf_counter()
        for _ in range(calls):
            rgb, labels = pool.render(qpos)
        dt = time.perf_counter() - t0
    assert rgb.shape == (batch, 84, 84, 3) and (labels == 2).any()
    return {
        "workers": workers,
        "tiles_per_sheet": tiles,
        "batch": batch,
        "calls": calls,
        "shadows_reflections": shadows,
        "seconds": dt,
        "obs_per_s": batch * calls / dt,
        "ms_per_call": 1e3 * dt / calls,
        "pool_start_s": start_s,
        "gl_renderer": info["GL_RENDERER"],
        "gl_vendor": info["GL_VENDOR"],
        "settings": dataclasses.asdict(settings),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="walker-walk")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 4, 8, 16])
    parser.add_argument("--tiles", type=int, nargs="+", default=[0], help="0 = auto")
    parser.add_argument("--batch", type=int, nargs="+", default=[1024])
    parser.add_argument("--calls", type=int, default=5)
    parser.add_argument("--shadows", action="store_true", help="shadows and reflections on")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    task = dmc.TASKS[args.task]
    rows = []
    print(f"{'workers':>7} {'tiles':>5} {'batch':>6} {'obs/s':>9} {'ms/call':>8}  GL_RENDERER")
    for batch in args.batch:
        for tiles in args.tiles:
            for workers in args.workers:
                row = measure(task, workers, tiles, batch, args.calls, args.shadows)
                rows.append(row)
                print(
                    f"{workers:>7} {tiles:>5} {batch:>6} {row['obs_per_s']:>9.0f} "
                    f"{row['ms_per_call']:>8.1f}  {row['gl_renderer']}",
                    flush=True,
                )
    result = {
        "benchmark": "render pool, RGB + labels, 84x84",
        "task": args.task,
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "rows": rows,
    }
    save_json(result, args.out)


if __name__ == "__main__":
    main()
