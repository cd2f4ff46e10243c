"""Render pool throughput per visual variant: observations (RGB + pixel labels) per second.

    python -m benchmarks.render --workers 16 --variants default fast default-in-place \
        no-reflection no-msaa no-shadow shadow2048 --out benchmarks/results/render_quality.json

One observation = one 84x84 RGB frame plus its label image, delivered to the caller as numpy
arrays (the pool's whole path: pickled qpos to the workers, kinematics, drawing, readback,
labels, shared memory, copy out). States are random poses of the task. Every variant, task,
worker count and tile count is one row, all in one invocation.

Each row also checks its picture: the first `--check` frames against mujoco.Renderer's default
frame of the same state drawn in this process (dm_control's picture: mean absolute difference in
levels of 255), and the labels against mujoco.Renderer's segmentation (pixels that differ). The
JSON records the GL renderer string, so a run on Mesa llvmpipe cannot pass for a GPU run.

`--workers 0` times one renderer in this process by its CPU time instead of a pool by the wall
clock: on a shared CPU-only machine the ratios between variants stay meaningful (with Mesa,
LP_NUM_THREADS=0 keeps rasterisation in this process's thread).

`--gpu-time` (with `--workers 0`) adds what the GPU spends on one call, by GL timer queries
(GL_TIME_ELAPSED) around each picture's drawing and copy into its sheet and each sheet's readback:
ms per observation for the RGB pictures, the segmentation pictures and the readbacks
(`gpu_ms_rgb`, `gpu_ms_labels`, `gpu_ms_readback`; each query's span, idle gaps included). That
is the GL work a training loop's updates wait behind when the frames are drawn on their GPU;
with Mesa, the CPU's rasterising.

`--mesh-faces N` draws every row with meshes simplified to about N faces (`env.render.mesh_faces`:
the kitchen's arm); |d| and the labels are still compared with mujoco.Renderer's picture of the
shipped meshes, and each row adds its checked frames' difference from the same variant drawn
with the shipped meshes (`*_vs_shipped_meshes`). `--primitives SxT` draws spheres, capsules and
cylinders with S slices and T stacks (`env.render.num_slices`, `num_stacks`; 0x0: the model's
own), each row adding its difference from the same variant drawn with the model's own
(`*_vs_model_primitives`).

`--gpus` draws each row's pool where `env.render.gpus` says: "auto", GPU numbers, or "cpu"
(Mesa's llvmpipe on the CPU's cores, whatever GPUs the machine has); the reference frames are
drawn in this process, on its default EGL device.

Variants: "default" and "fast" are the two qualities (envs/render.py); the others change one
thing of "default": an effect off, another shadow map size, or "-in-place" (each picture drawn in
its place on a sheet-sized MuJoCo buffer, the layout before pictures were drawn at the origin and
copied); "-no-labels" skips the segmentation pass (`RenderSettings.labels`: labels all 0, the
envs of methods that read no mask and composite no background).
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import itertools
import os
import platform
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.common import save_json  # noqa: E402
from envs import dmc, kitchen  # noqa: E402
from envs.labels import label_tables, labels_from_segmentation  # noqa: E402
from envs.render import QUALITY_VISUALS, RenderSettings, TileRenderer  # noqa: E402
from envs.render_pool import RenderPool  # noqa: E402

_DM = QUALITY_VISUALS["dm_control"]
VARIANTS = {
    "default": RenderSettings(quality="dm_control"),
    "fast": RenderSettings(quality="fast"),
    "default-in-place": RenderSettings(quality="dm_control", in_place=True),
    "fast-in-place": RenderSettings(quality="fast", in_place=True),
    "default-no-labels": RenderSettings(quality="dm_control", labels=False),
    "fast-no-labels": RenderSettings(quality="fast", labels=False),
    "no-reflection": RenderSettings(visuals=dataclasses.replace(_DM, reflections=False)),
    "no-msaa": RenderSettings(visuals=dataclasses.replace(_DM, multisample=False)),
    "no-shadow": RenderSettings(visuals=dataclasses.replace(_DM, shadows=False)),
    "no-skybox": RenderSettings(visuals=dataclasses.replace(_DM, skybox=False)),
    "shadow2048": RenderSettings(visuals=dataclasses.replace(_DM, shadow_size=None)),
    "shadow512": RenderSettings(visuals=dataclasses.replace(_DM, shadow_size=512)),
    "shadow128": RenderSettings(visuals=dataclasses.replace(_DM, shadow_size=128)),
    "shadow2048-in-place": RenderSettings(
        visuals=dataclasses.replace(_DM, shadow_size=None), in_place=True
    ),
}


TASKS = {**dmc.TASKS, **kitchen.TASKS}


def random_states(model: mujoco.MjModel, batch: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.tile(model.qpos0, (batch, 1)) + rng.normal(0, 0.3, (batch, model.nq))


def reference(task, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """mujoco.Renderer's default frames and labels (from its segmentation) of these states."""
    model = task.render_model()
    data = mujoco.MjData(model)
    tables = label_tables(model, task.agent_geom_ids(model), task.floor_geom_ids(model))
    rgb, labels = [], []
    with mujoco.Renderer(model, 84, 84) as renderer:
        for q in qpos:
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, task.camera)
            rgb.append(renderer.render())
            renderer.enable_segmentation_rendering()
            labels.append(labels_from_segmentation(renderer.render(), tables))
            renderer.disable_segmentation_rendering()
    return np.stack(rgb), np.stack(labels)


def gpu_times(renderer: TileRenderer, qpos: np.ndarray) -> dict[str, float]:
    """The GPU's time for one `renderer.render(qpos)` (after an untimed one: a new context's
    first queries can read garbage), in ms per observation, from timer queries around the
    renderer's own steps: each picture's drawing and copy (RGB and segmentation apart, told by
    the scene's segmentation flag) and each sheet's readback. A query spans the GPU's time
    from its start to its end, idle gaps within included: an upper bound of its busy time."""
    from OpenGL import GL

    batch, h, w = qpos.shape[0], renderer.settings.height, renderer.settings.width
    rgb, labels = np.empty((batch, h, w, 3), np.uint8), np.empty((batch, h, w), np.uint8)
    renderer.render(qpos, rgb, labels)
    queries = {"rgb": [], "labels": [], "readback": []}
    draw, read = renderer._draw, renderer._read
    segment = mujoco.mjtRndFlag.mjRND_SEGMENT

    def timed(kind, step, *args):
        query = int(GL.glGenQueries(1)[0])
        queries[kind].append(query)
        GL.glBeginQuery(GL.GL_TIME_ELAPSED, query)
        try:
            step(*args)
        finally:
            GL.glEndQuery(GL.GL_TIME_ELAPSED)

    renderer._draw = lambda *a: timed(
        "labels" if renderer.scene.flags[segment] else "rgb", draw, *a
    )
    renderer._read = lambda *a: timed("readback", read, *a)
    try:
        renderer.render(qpos, rgb, labels)
    finally:
        del renderer._draw, renderer._read  # the instance's wrappers; the methods again
    elapsed, times = ctypes.c_uint64(), {}
    for kind, ids in queries.items():
        total = 0
        for query in ids:
            GL.glGetQueryObjectui64v(query, GL.GL_QUERY_RESULT, ctypes.byref(elapsed))
            total += elapsed.value
            GL.glDeleteQueries(1, [query])
        times[f"gpu_ms_{kind}"] = total / 1e6 / batch
    return times


def measure(
    task,
    variant,
    workers,
    tiles,
    qpos,
    calls,
    ref_rgb,
    ref_labels,
    mesh_faces=0,
    primitives=(0, 0),
    gpu_time=False,
    gpus="auto",
):
    """Pool throughput (wall clock), or with workers=0 one TileRenderer in this process timed by
    this process's CPU time (best of `calls`): a proxy that other load on the machine barely moves;
    gpu_time (workers=0): with `gpu_times` of one more call."""
    settings = dataclasses.replace(
        VARIANTS[variant],
        num_workers=workers,
        tiles_per_sheet=tiles,
        mesh_faces=mesh_faces,
        num_slices=primitives[0],
        num_stacks=primitives[1],
        gpus=gpus,
    )
    model = task.render_model(mesh_faces)
    agent, floor = task.agent_geom_ids(model), task.floor_geom_ids(model)
    t0 = time.perf_counter()
    if workers == 0:
        renderer = TileRenderer(
            model, camera=task.camera, agent_geom_ids=agent, floor_geom_ids=floor, settings=settings
        )
        start_s = time.perf_counter() - t0
        info = renderer.gl_info()
        rgb = np.zeros((len(qpos), 84, 84, 3), np.uint8)
        labels = np.zeros((len(qpos), 84, 84), np.uint8)
        renderer.render(qpos, rgb, labels)
        best = np.inf
        for _ in range(calls):
            t0 = time.process_time()
            renderer.render(qpos, rgb, labels)
            best = min(best, time.process_time() - t0)
        gpu = gpu_times(renderer, qpos) if gpu_time else {}
        renderer.close()
        dt = best * calls
    else:
        gpu = {}
        with RenderPool(
            task.render_factory(mesh_faces),
            camera=task.camera,
            agent_geom_ids=agent,
            floor_geom_ids=floor,
            settings=settings,
        ) as pool:
            start_s = time.perf_counter() - t0
            info = pool.gl_info()[0]
            rgb, labels = pool.render(qpos)  # warm-up: shared memory, GL state
            t0 = time.perf_counter()
            for _ in range(calls):
                pool.render(qpos)
            dt = time.perf_counter() - t0
    n = len(ref_rgb)
    diff = np.abs(rgb[:n].astype(np.int16) - ref_rgb)
    batch = qpos.shape[0]

    def versus(suffix, **change):
        """The checked frames' difference from the same variant drawn with `change`."""
        same = dataclasses.replace(settings, **change)
        renderer = TileRenderer(
            task.render_model(same.mesh_faces),
            camera=task.camera,
            agent_geom_ids=agent,
            floor_geom_ids=floor,
            settings=same,
        )
        other_rgb, other_labels = np.zeros_like(rgb[:n]), np.zeros_like(labels[:n])
        renderer.render(qpos[:n], other_rgb, other_labels)
        renderer.close()
        gap = np.abs(rgb[:n].astype(np.int16) - other_rgb)
        return {
            f"mean_abs_diff_vs_{suffix}": float(gap.mean()),
            f"worst_frame_mean_abs_diff_vs_{suffix}": float(gap.mean(axis=(1, 2, 3)).max()),
            f"label_pixels_differing_vs_{suffix}": int((labels[:n] != other_labels).sum()),
        }

    compared = {}
    if mesh_faces:  # the same variant on the shipped meshes: what the simplification alone changes
        compared.update(versus("shipped_meshes", mesh_faces=0))
    if any(primitives):
        compared.update(versus("model_primitives", num_slices=0, num_stacks=0))
    return {
        **compared,
        **gpu,
        "task": task.name,
        "variant": variant,
        "workers": workers,
        "tiles_per_sheet": tiles,
        "batch": batch,
        "calls": calls,
        "seconds": dt,
        "obs_per_s": batch * calls / dt,
        "ms_per_call": 1e3 * dt / calls,
        "pool_start_s": start_s,
        "frames_checked": n,
        "mean_abs_diff_vs_renderer": float(diff.mean()),
        "worst_frame_mean_abs_diff": float(diff.mean(axis=(1, 2, 3)).max()),
        "label_pixels_differing": int((labels[:n] != ref_labels).sum()),
        "gl_renderer": info["GL_RENDERER"],
        "gl_vendor": info["GL_VENDOR"],
        "settings": dataclasses.asdict(settings),
        "visuals": dataclasses.asdict(settings.resolved_visuals()),
    }


def _slices_by_stacks(text: str) -> tuple[int, int]:
    slices, sep, stacks = text.partition("x")
    if not (sep and slices.isdigit() and stacks.isdigit()):
        raise argparse.ArgumentTypeError(
            f"{text!r}: give SLICESxSTACKS, e.g. 16x4 (0x0: the model's)"
        )
    return int(slices), int(stacks)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["walker-walk"], choices=sorted(TASKS))
    parser.add_argument("--variants", nargs="+", default=["default", "fast"], choices=VARIANTS)
    parser.add_argument(
        "--workers", type=int, nargs="+", default=[16], help="0 = in this process, CPU time"
    )
    parser.add_argument("--tiles", type=int, nargs="+", default=[0], help="0 = auto")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--calls", type=int, default=5)
    parser.add_argument("--check", type=int, default=16, help="frames compared with the renderer")
    parser.add_argument(
        "--mesh-faces",
        type=int,
        nargs="+",
        default=[0],
        help="env.render.mesh_faces (0: as shipped)",
    )
    parser.add_argument(
        "--primitives",
        type=_slices_by_stacks,
        nargs="+",
        default=[(0, 0)],
        help="SLICESxSTACKS of spheres, capsules, cylinders (env.render.num_slices, num_stacks; "
        "0x0: the model's own)",
    )
    parser.add_argument(
        "--gpu-time",
        action="store_true",
        help="with --workers 0: the GPU's ms per observation by GL timer queries",
    )
    parser.add_argument(
        "--gpus",
        nargs="+",
        default=["auto"],
        help="env.render.gpus of the pool's workers, one row each (cpu: Mesa's llvmpipe)",
    )
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if 0 in args.workers and set(args.gpus) != {"auto"}:
        parser.error(
            "--workers 0 draws in this process, on its default device: --gpus applies to pools "
            f"(--workers 1 or more), got --gpus {' '.join(args.gpus)}"
        )
    if args.gpu_time and any(args.workers):
        parser.error(
            f"--gpu-time times one renderer in this process: give --workers 0, not {args.workers}"
        )
    rows = []
    head = (
        f"{'task':<18} {'variant':<20} {'gpus':>5} {'workers':>7} {'tiles':>5} {'obs/s':>8} {'x fast':>6} "
        f"{'ms/call':>8} {'|d| vs Renderer':>15} {'label px':>8} {'faces':>6} {'|d| vs shipped':>14} "
        f"{'primitives':>10} {'|d| vs model':>12}"
    )
    print(head)
    for name in args.tasks:
        task = TASKS[name]
        qpos = random_states(task.render_model(), args.batch)
        ref_rgb, ref_labels = reference(task, qpos[: args.check])
        grid = itertools.product(
            args.gpus, args.workers, args.tiles, args.mesh_faces, args.primitives
        )
        for gpus, workers, tiles, faces, primitives in grid:
            fast_obs = None
            for variant in sorted(args.variants, key=lambda v: v != "fast"):  # fast first
                where = f"{name:<18} {variant:<20} {gpus:>5} {workers:>7} {tiles:>5}"
                try:
                    row = measure(
                        task,
                        variant,
                        workers,
                        tiles,
                        qpos,
                        args.calls,
                        ref_rgb,
                        ref_labels,
                        faces,
                        primitives,
                        args.gpu_time,
                        gpus,
                    )
                except Exception as err:  # noqa: BLE001 - one variant must not end the run
                    rows.append(
                        dict(
                            task=name,
                            variant=variant,
                            workers=workers,
                            tiles=tiles,
                            mesh_faces=faces,
                            primitives=list(primitives),
                            gpus=gpus,
                            error=repr(err),
                        )
                    )
                    print(f"{where} failed: {err!r}", flush=True)
                    continue
                rows.append(row)
                fast_obs = row["obs_per_s"] if variant == "fast" else fast_obs
                rel = f"{row['obs_per_s'] / fast_obs:6.3f}" if fast_obs else f"{'':>6}"
                print(
                    f"{where} {row['obs_per_s']:>8.0f} {rel} {row['ms_per_call']:>8.1f} "
                    f"{row['mean_abs_diff_vs_renderer']:>15.3f} "
                    f"{row['label_pixels_differing']:>8} {faces:>6} "
                    f"{row.get('mean_abs_diff_vs_shipped_meshes', 0.0):>14.3f} "
                    f"{'x'.join(map(str, primitives)):>10} "
                    f"{row.get('mean_abs_diff_vs_model_primitives', 0.0):>12.3f}"
                    + (
                        f"  GPU ms/obs: RGB {row['gpu_ms_rgb']:.4f}, labels "
                        f"{row['gpu_ms_labels']:.4f}, readback {row['gpu_ms_readback']:.4f}"
                        if args.gpu_time
                        else ""
                    ),
                    flush=True,
                )
    print("GL_RENDERER:", {row["gl_renderer"] for row in rows if "gl_renderer" in row})
    result = {
        "benchmark": "render pool per visual variant, RGB + labels, 84x84",
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "args": vars(args),
        "rows": rows,
    }
    save_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
