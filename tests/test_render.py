"""Render pool: frames are dm_control's (mujoco.Renderer's); labels follow MuJoCo's segmentation."""

import copy
import dataclasses
import functools
import importlib.util
import json
import os
import pathlib
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest

from configs import base as base_config
from configs import smoke as smoke_config
from envs import dmc
from envs import render as R
from envs.camera import cart_to_sphere
from envs.labels import (
    LABEL_AGENT,
    LABEL_BACKGROUND,
    LABEL_FLOOR,
    LABEL_OTHER,
    label_tables,
    labels_from_segmentation,
)
from envs.render_pool import RenderPool

SUITE = pathlib.Path(importlib.util.find_spec("dm_control").origin).parent / "suite"


def load(xml: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(SUITE / xml))


def subtree_geoms(model, body_names):
    roots = {model.body(b).id for b in body_names}
    ids = []
    for g in range(model.ngeom):
        b = model.geom_bodyid[g]
        while b != 0 and b not in roots:
            b = model.body_parentid[b]
        if b in roots:
            ids.append(g)
    return ids


# task -> (xml, agent bodies, floor geom, camera); docs/method.md's agents (Masks).
TASKS = {
    "walker": ("walker.xml", ("torso",), "floor", 0),
    "cup": ("ball_in_cup.xml", ("cup", "ball"), "ground", 0),
    "finger": ("finger.xml", ("proximal",), "ground", 0),
}


def task_facts(name):
    xml, bodies, floor, cam = TASKS[name]
    model = load(xml)
    return model, subtree_geoms(model, bodies), [model.geom(floor).id], cam


def random_qpos(model, n, seed, scale=0.4):
    rng = np.random.default_rng(seed)
    qpos = np.tile(model.qpos0, (n, 1)) + rng.normal(0.0, scale, (n, model.nq))
    return qpos


def reference_render(model, qpos, cam, visuals=None, size=84):
    """mujoco.Renderer after mj_forward: RGB and (object id, object type) segmentation.

    visuals None: mujoco.Renderer's own defaults, which are dm_control's picture."""
    model = copy.deepcopy(model)
    if visuals is not None:
        R.apply_visuals(model, visuals)
    data = mujoco.MjData(model)
    rgbs, segs = [], []
    with mujoco.Renderer(model, size, size) as renderer:
        if visuals is not None:
            R.apply_scene_flags(renderer.scene, visuals)
        for q in qpos:
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, cam)
            rgbs.append(renderer.render())
            renderer.enable_segmentation_rendering()
            segs.append(renderer.render())
            renderer.disable_segmentation_rendering()
    return np.stack(rgbs), np.stack(segs)


def tile_render(model, qpos, cam, agent, floor, settings, labels_fill=0, before=None, **kwargs):
    """TileRenderer's frames and labels; labels_fill: what the labels buffer held before;
    before: called with the renderer before it draws them."""
    tr = R.TileRenderer(
        copy.deepcopy(model),
        camera=cam,
        agent_geom_ids=agent,
        floor_geom_ids=floor,
        settings=settings,
    )
    try:
        if before is not None:
            before(tr)
        rgb = np.zeros((len(qpos), settings.height, settings.width, 3), np.uint8)
        labels = np.full((len(qpos), settings.height, settings.width), labels_fill, np.uint8)
        tr.render(qpos, rgb, labels, **kwargs)
        return rgb, labels
    finally:
        tr.close()


def model_pool(model, agent, floor, cam, settings):
    """A render pool whose workers draw copies of `model`."""
    return RenderPool(
        functools.partial(copy.deepcopy, model),
        camera=cam,
        agent_geom_ids=agent,
        floor_geom_ids=floor,
        settings=settings,
    )


def pool_render(task, qpos, settings):
    """The env's path: spawned workers building the task's render model, the task's camera."""
    model = task.render_model()
    with RenderPool(
        functools.partial(dmc.render_model_fn, task.name),
        camera=task.camera,
        agent_geom_ids=task.agent_geom_ids(model),
        floor_geom_ids=task.floor_geom_ids(model),
        settings=settings,
    ) as pool:
        return pool.render(qpos)


DMC_NAMES = {"walker": "walker-walk", "cup": "ball_in_cup-catch", "finger": "finger-spin"}


@pytest.mark.parametrize("name", ["walker", "cup", "finger"])
def test_default_frames_are_dm_controls(name):
    """The default quality draws what dm_control's physics.render(84, 84, camera_id) draws:
    mujoco.Renderer's default frame after mj_forward (skybox, shadows, reflections, the model's
    multisampling), from DrQ-v2's camera (0 for these tasks). Measured per-frame mean absolute
    difference (levels of 255; these 4 random states; Mesa llvmpipe): walker <= 0.052, cup
    <= 0.078, finger <= 0.018, all from the 256-texel shadow map (with 2048 texels: 0). "fast" is
    a different picture (black sky, no shadows or reflections): 32-45 levels away. Labels are the
    same under both qualities. The bound, 0.25, is 3x the largest measured difference and below
    what turning one effect off moves a frame (reflections 0.41, multisampling 0.67 levels on an
    H100: benchmarks/RESULTS.md, "Render quality and speed")."""
    task = dmc.TASKS[DMC_NAMES[name]]
    assert task.camera == 0  # DrQ-v2: camera_id = 2 if domain == "quadruped" else 0
    model = task.render_model()
    qpos = random_qpos(model, 4, seed=7, scale=0.3)
    rgb, labels = pool_render(task, qpos, R.RenderSettings(num_workers=1))
    fast_rgb, fast_labels = pool_render(task, qpos, R.RenderSettings(num_workers=1, quality="fast"))
    ref_rgb, ref_seg = reference_render(model, qpos, task.camera)

    def frame_diff(x):
        return np.abs(x.astype(int) - ref_rgb).mean(axis=(1, 2, 3))

    assert frame_diff(rgb).max() <= 0.25, frame_diff(rgb)
    assert frame_diff(fast_rgb).min() >= 20.0, frame_diff(fast_rgb)
    tables = label_tables(model, task.agent_geom_ids(model), task.floor_geom_ids(model))
    np.testing.assert_array_equal(labels, labels_from_segmentation(ref_seg, tables))
    np.testing.assert_array_equal(fast_labels, labels)


def test_quality_is_one_named_choice():
    """configs: dm_control's picture by default, fast for the CPU smoke run; others refused."""
    assert R.RenderSettings().quality == "dm_control"
    base = R.RenderSettings(**base_config.get_config().env.render.to_dict())
    smoke = R.RenderSettings(**smoke_config.get_config().env.render.to_dict())
    assert (base.quality, smoke.quality) == ("dm_control", "fast")
    assert base.resolved_visuals() == R.QUALITY_VISUALS["dm_control"]
    with pytest.raises(
        ValueError, match="unknown render quality 'pretty'; valid: dm_control, fast"
    ):
        R.RenderSettings(quality="pretty")


_FORKSERVER_SIGNALS = """
import multiprocessing.forkserver, multiprocessing.resource_tracker, os, signal, time
from envs import forkserver
child = forkserver.context().Process(target=time.sleep, args=(2.0,))
child.start()
server = multiprocessing.forkserver._forkserver._forkserver_pid
tracker = multiprocessing.resource_tracker._resource_tracker._pid
for pid in (server, tracker):
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        os.kill(pid, sig)
time.sleep(0.5)
for pid in (server, tracker):
    os.kill(pid, 0)  # ProcessLookupError if it died
assert child.is_alive(), child.exitcode
child.join()
print("exit", child.exitcode, signal.pthread_sigmask(signal.SIG_BLOCK, ()))
"""


def test_the_fork_server_outlives_a_stop_signal_to_the_process_group():
    """The render workers' and evaluation processes' fork server, and multiprocessing's resource
    tracker, never see the stop signals: a signal to the whole group leaves them serving, and the
    fork server's children read as alive until they end (had it died, is_alive() would say its
    children died with exit code 255); this process's own signal mask is as it was."""
    import subprocess
    import sys

    root = pathlib.Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", _FORKSERVER_SIGNALS],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["exit", "0", "set()"]


def test_the_number_of_workers_follows_the_settings_the_cores_and_the_batch(monkeypatch):
    """num_workers > 0 is taken as it is; 0 is min(cores, 8), and with envs_per_worker K no more
    than one worker per K samples of the pool's batch (when it is known); drawn on the CPU,
    cores - 1 (at least one)."""
    monkeypatch.setattr(R.os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    assert R.RenderSettings(num_workers=3).resolved_workers(batch=1) == 3
    assert R.RenderSettings().resolved_workers(batch=5) == 8
    capped = R.RenderSettings(envs_per_worker=8)
    assert [capped.resolved_workers(b) for b in (None, 1, 5, 16, 17, 48, 160)] == [
        8,
        1,
        1,
        2,
        3,
        6,
        8,
    ]
    # Drawn on the CPU: a worker per core but one, whatever the batch.
    on_cpu = R.RenderSettings(gpus="cpu", envs_per_worker=8)
    assert [on_cpu.resolved_workers(b) for b in (None, 1, 80)] == [15, 15, 15]
    monkeypatch.setattr(R.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert capped.resolved_workers(48) == 2 and R.RenderSettings().resolved_workers() == 2
    assert on_cpu.resolved_workers(80) == 1
    with pytest.raises(ValueError, match="envs_per_worker must be 0 \\(auto\\) or more, got -1"):
        R.RenderSettings(envs_per_worker=-1)


@pytest.mark.parametrize("task", ["walker", "cup"])
def test_pool_equals_single_process_renderer(task):
    """Two spawned workers, shared memory, one tile per sheet: bit-identical to mujoco.Renderer
    with the same visuals after mj_forward (random cup states stretch the string past its limit:
    drawn red)."""
    model, agent, floor, cam = task_facts(task)
    settings = R.RenderSettings(num_workers=2, tiles_per_sheet=1)
    qpos = random_qpos(model, 5, seed=1)
    with model_pool(model, agent, floor, cam, settings) as pool:
        rgb, labels = pool.render(qpos)
        # a second, smaller batch reuses the same shared block
        rgb2, labels2 = pool.render(qpos[3:])
    ref_rgb, ref_seg = reference_render(model, qpos, cam, settings.resolved_visuals())
    assert rgb.dtype == np.uint8 and rgb.shape == (5, 84, 84, 3) and labels.shape == (5, 84, 84)
    np.testing.assert_array_equal(rgb, ref_rgb)
    np.testing.assert_array_equal(rgb2, ref_rgb[3:])
    np.testing.assert_array_equal(labels2, labels[3:])
    tables = label_tables(model, agent, floor)
    np.testing.assert_array_equal(labels, labels_from_segmentation(ref_seg, tables))


@pytest.mark.parametrize("task", ["walker", "cup", "finger"])
def test_mask_lies_exactly_on_agent_geoms(task):
    """Agent label <=> MuJoCo's segmentation shows an agent geom (checked independently)."""
    model, agent, floor, cam = task_facts(task)
    settings = R.RenderSettings(tiles_per_sheet=1)
    qpos = random_qpos(model, 4, seed=2, scale=0.2)
    _, labels = tile_render(model, qpos, cam, agent, floor, settings)
    _, seg = reference_render(model, qpos, cam)
    objid, objtype = seg[..., 0], seg[..., 1]
    is_geom = objtype == mujoco.mjtObj.mjOBJ_GEOM
    on_agent = is_geom & np.isin(objid, agent)
    on_floor = is_geom & np.isin(objid, floor)
    mask = labels == LABEL_AGENT
    assert mask.sum(axis=(1, 2)).min() > 20, "every frame shows the agent"
    np.testing.assert_array_equal(mask, on_agent)
    np.testing.assert_array_equal(labels == LABEL_FLOOR, on_floor)
    np.testing.assert_array_equal(labels == LABEL_BACKGROUND, objtype == -1)


def test_tendon_and_sites_are_not_agent():
    """The cup's string (tendon) and its visible sites are drawn but labelled OTHER."""
    model, agent, floor, cam = task_facts("cup")
    # A big picture of a stretched string, so the tendon covers many pixels.
    settings = R.RenderSettings(width=480, height=480, tiles_per_sheet=1)
    qpos = np.array([[0.0, 0.0, 0.1, 0.0]])  # ball 0.3 below the cup and aside: a long string
    _, labels = tile_render(model, qpos, cam, agent, floor, settings)
    _, seg = reference_render(model, qpos, cam, size=480)
    tendon = seg[..., 1] == mujoco.mjtObj.mjOBJ_TENDON
    site = seg[..., 1] == mujoco.mjtObj.mjOBJ_SITE
    assert tendon.sum() > 10 and site.sum() > 0, "the string and a site are visible"
    assert (labels[tendon] == LABEL_OTHER).all()
    assert (labels[site] == LABEL_OTHER).all()


@pytest.mark.parametrize("quality", R.QUALITIES)
def test_tiles_of_a_sheet_are_renderer_frames(quality):
    """24 samples on sheets of 20 (16 across, 2 rows): every tile is mujoco.Renderer's frame of
    its state bit for bit (each picture has its own shadow map, reflection and skybox passes at
    the buffer's origin), and the labels are exact."""
    model, agent, floor, cam = task_facts("walker")
    settings = R.RenderSettings(tiles_per_sheet=20, quality=quality)
    qpos = random_qpos(model, 24, seed=3)
    rgb, labels = tile_render(model, qpos, cam, agent, floor, settings)
    ref_rgb, ref_seg = reference_render(model, qpos, cam, settings.resolved_visuals())
    tables = label_tables(model, agent, floor)
    np.testing.assert_array_equal(labels, labels_from_segmentation(ref_seg, tables))
    np.testing.assert_array_equal(rgb, ref_rgb)


def test_without_labels_the_frames_are_the_same_and_the_labels_background():
    """labels=False skips the segmentation pass: every tile is still mujoco.Renderer's frame bit
    for bit, and every label is LABEL_BACKGROUND (also where a sheet held labels before)."""
    model, agent, floor, cam = task_facts("walker")
    qpos = random_qpos(model, 6, seed=4)
    with_labels = tile_render(model, qpos, cam, agent, floor, R.RenderSettings(tiles_per_sheet=4))
    settings = R.RenderSettings(tiles_per_sheet=4, labels=False)
    rgb, labels = tile_render(model, qpos, cam, agent, floor, settings, labels_fill=LABEL_AGENT)
    np.testing.assert_array_equal(rgb, with_labels[0])
    assert (with_labels[1] == LABEL_AGENT).any() and (labels == LABEL_BACKGROUND).all()


def test_primitives_drawn_with_the_slices_and_stacks_asked_for():
    """num_slices / num_stacks are the model's vis.quality.numslices / numstacks as the renderer
    draws: the walker's capsules at 16 x 4 are mujoco.Renderer's frames of a model so set, bit
    for bit, and a little off the 28 x 16 frames (MuJoCo's defaults, which the walker keeps: 0
    draws them, as does asking for them). Labels keep the agent within a few pixels' edges."""
    model, agent, floor, cam = task_facts("walker")
    assert (model.vis.quality.numslices, model.vis.quality.numstacks) == (28, 16)
    qpos = random_qpos(model, 4, seed=5)
    fast = R.RenderSettings(tiles_per_sheet=4, quality="fast")
    rgb, labels = tile_render(model, qpos, cam, agent, floor, fast)
    same = R.RenderSettings(tiles_per_sheet=4, quality="fast", num_slices=28, num_stacks=16)
    np.testing.assert_array_equal(tile_render(model, qpos, cam, agent, floor, same)[0], rgb)
    coarse = R.RenderSettings(tiles_per_sheet=4, quality="fast", num_slices=16, num_stacks=4)
    coarse_rgb, coarse_labels = tile_render(model, qpos, cam, agent, floor, coarse)
    ref = copy.deepcopy(model)
    ref.vis.quality.numslices, ref.vis.quality.numstacks = 16, 4
    ref_rgb, ref_seg = reference_render(ref, qpos, cam, coarse.resolved_visuals())
    np.testing.assert_array_equal(coarse_rgb, ref_rgb)
    tables = label_tables(model, agent, floor)
    np.testing.assert_array_equal(coarse_labels, labels_from_segmentation(ref_seg, tables))
    diff = np.abs(coarse_rgb.astype(int) - rgb).mean()
    assert 0 < diff < 1.0, diff
    agent_pixels = labels == LABEL_AGENT
    assert (coarse_labels != labels).sum() < 0.05 * agent_pixels.sum()
    assert (R.MIN_SLICES, R.MIN_STACKS) == (8, 2)  # one stack draws no sphere
    for name, least in (("num_slices", R.MIN_SLICES), ("num_stacks", R.MIN_STACKS)):
        for bad in (-1, least - 1):
            with pytest.raises(
                ValueError, match=rf"{name} must be 0 \(the model's own\) or >= {least}"
            ):
                R.RenderSettings(**{name: bad})


def test_labels_drawn_for_the_rows_asked_for():
    """label_rows draws the segmentation pass for those samples only (the evaluation's video
    env): their labels are exact, the others' all LABEL_BACKGROUND (also where the buffer held
    labels before), every frame the same; without settings.labels none is drawn. A pool's
    workers each draw their slice of the rows."""
    model, agent, floor, cam = task_facts("walker")
    qpos = random_qpos(model, 6, seed=4)
    settings = R.RenderSettings(tiles_per_sheet=4)
    rgb, labels = tile_render(model, qpos, cam, agent, floor, settings)
    rows = np.array([True, False, True, False, False, True])
    some = tile_render(model, qpos, cam, agent, floor, settings, LABEL_AGENT, label_rows=rows)
    np.testing.assert_array_equal(some[0], rgb)
    np.testing.assert_array_equal(some[1][rows], labels[rows])
    assert (labels[~rows] == LABEL_AGENT).any() and (some[1][~rows] == LABEL_BACKGROUND).all()
    off = dataclasses.replace(settings, labels=False)
    none = tile_render(model, qpos, cam, agent, floor, off, LABEL_AGENT, label_rows=rows)
    assert (none[1] == LABEL_BACKGROUND).all()
    # A pool hands each worker its slice of the rows: 3 workers split the 6 samples 2, 2, 2.
    with model_pool(model, agent, floor, cam, R.RenderSettings(num_workers=3)) as pool:
        pooled = pool.render(qpos, label_rows=rows)
    np.testing.assert_array_equal(pooled[0], rgb)
    np.testing.assert_array_equal(pooled[1], some[1])


def test_render_benchmark_compares_coarser_primitives_with_the_models(tmp_path):
    """benchmarks/render.py --primitives: a row per SLICESxSTACKS, each coarser one with its
    frames' difference from the model's own primitives (small, not zero), the settings it drew
    with in the JSON; a malformed value is named."""
    from benchmarks import render as bench

    out = tmp_path / "render.json"
    argv = "--tasks walker-walk --workers 0 --batch 4 --calls 1 --check 2 --variants fast"
    result = bench.main([*argv.split(), "--primitives", "0x0", "16x4", "--out", str(out)])
    model_own, coarse = result["rows"]
    assert "mean_abs_diff_vs_model_primitives" not in model_own
    assert 0 < coarse["mean_abs_diff_vs_model_primitives"] < 1.0
    assert (coarse["settings"]["num_slices"], coarse["settings"]["num_stacks"]) == (16, 4)
    assert json.loads(out.read_text())["rows"][1]["settings"]["num_stacks"] == 4
    with pytest.raises(SystemExit):
        bench.main([*argv.split(), "--primitives", "16"])


def test_render_benchmark_draws_each_row_where_gpus_says():
    """benchmarks/render.py --gpus: a pool row per setting, drawn where it says ("cpu": Mesa's
    llvmpipe, whatever the default device), the setting in the row's JSON; refused for the
    renderer in this process (--workers 0)."""
    from benchmarks import render as bench

    argv = "--tasks walker-walk --workers 1 --batch 4 --calls 1 --check 2 --variants fast"
    rows = bench.main([*argv.split(), "--gpus", "auto", "cpu"])["rows"]
    assert [row["settings"]["gpus"] for row in rows] == ["auto", "cpu"]
    assert "llvmpipe" in rows[1]["gl_renderer"]
    assert rows[1]["label_pixels_differing"] <= 20  # against labels drawn on the default device
    with pytest.raises(SystemExit):  # a renderer in this process draws on its default device
        bench.main(["--workers", "0", "--gpus", "cpu"])


def test_render_benchmark_times_the_gl_work_of_rgb_and_label_pictures():
    """benchmarks/render.py --gpu-time: the timer queries time both kinds of picture (RGB and
    segmentation; none of the second without the segmentation pass), in milliseconds (the
    order of a call's time; how long is the benchmark's to say); the renderer draws the same
    frames after them, its own steps back in place; the flag asks for one renderer in this
    process."""
    from benchmarks import render as bench

    model, agent, floor, cam = task_facts("walker")
    qpos = random_qpos(model, 3, seed=2)
    times = {}

    def timed_first(tr):
        times[tr.settings] = bench.gpu_times(tr, qpos)
        t0 = time.perf_counter()  # a call like the timed one, by the clock
        tr.render(qpos, *(np.empty_like(a) for a in untimed))
        times[tr.settings]["wall_ms"] = 1e3 * (time.perf_counter() - t0) / len(qpos)
        assert "_draw" not in vars(tr) and "_read" not in vars(tr)

    fast, effects = R.RenderSettings(quality="fast"), R.RenderSettings(quality="dm_control")
    no_labels = R.RenderSettings(quality="fast", labels=False)
    untimed = tile_render(model, qpos, cam, agent, floor, fast)
    after_timing = tile_render(model, qpos, cam, agent, floor, fast, before=timed_first)
    for a, b in zip(after_timing, untimed):
        np.testing.assert_array_equal(a, b)
    for settings in (effects, no_labels):
        tile_render(model, qpos, cam, agent, floor, settings, before=timed_first)
    for t in times.values():  # milliseconds: not above a call's time by orders of magnitude
        assert 0 < t["gpu_ms_rgb"] and t["gpu_ms_rgb"] + t["gpu_ms_labels"] < 10 * t["wall_ms"]
    assert times[fast]["gpu_ms_labels"] > 0 and times[no_labels]["gpu_ms_labels"] == 0
    argv = "--tasks walker-walk --batch 4 --calls 1 --check 2 --variants fast --gpu-time"
    with pytest.raises(SystemExit):
        bench.main([*argv.split(), "--workers", "2"])


def test_in_place_sheet_matches_renderer_up_to_rasterisation():
    """The measuring layout (pictures drawn in place on a sheet-sized buffer): labels exact; RGB
    off in under 0.2% of pixels (0.07% on Mesa llvmpipe)."""
    model, agent, floor, cam = task_facts("walker")
    settings = R.RenderSettings(tiles_per_sheet=20, in_place=True)
    qpos = random_qpos(model, 24, seed=3)
    rgb, labels = tile_render(model, qpos, cam, agent, floor, settings)
    ref_rgb, ref_seg = reference_render(model, qpos, cam, settings.resolved_visuals())
    tables = label_tables(model, agent, floor)
    np.testing.assert_array_equal(labels, labels_from_segmentation(ref_seg, tables))
    diff = np.abs(rgb.astype(int) - ref_rgb)
    assert (diff.max(-1) > 0).mean() < 0.002


def test_colour_perturbation_changes_pixels_not_labels():
    model, agent, floor, cam = task_facts("walker")
    settings = R.RenderSettings(tiles_per_sheet=1)
    qpos = random_qpos(model, 3, seed=5)
    rng = np.random.default_rng(0)
    mat_rgb = np.clip(
        model.mat_rgba[None, :, :3] + rng.uniform(-0.3, 0.3, (3, model.nmat, 3)), 0, 1
    )
    rgb0, labels0 = tile_render(model, qpos, cam, agent, floor, settings)
    rgb1, labels1 = tile_render(
        model, qpos, cam, agent, floor, settings, perturb={"mat_rgb": mat_rgb.astype(np.float32)}
    )
    # Colours move no geometry: every label stays; agent pixels change colour.
    np.testing.assert_array_equal(labels1, labels0)
    agent_px = labels0 == LABEL_AGENT
    changed = (rgb1 != rgb0).any(-1)
    assert changed[agent_px].mean() > 0.9


def camera_sphere(model, cam):
    """The unperturbed camera's own (radius, h, v, roll=0) relative to the agent's com."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return np.append(cart_to_sphere(data.cam_xpos[cam] - data.subtree_com[1]), 0.0)


def test_camera_perturbation_geometry():
    """Zero perturbation reproduces the picture; zooming in by r -> 0.8 r grows the agent ~1/0.8^2;
    a roll of 90 degrees turns the mask by 90 degrees about the image centre (near enough)."""
    model, agent, floor, cam = task_facts("walker")
    settings = R.RenderSettings(tiles_per_sheet=1)
    qpos = model.qpos0[None].copy()
    qpos[0, 1] = 0.2  # torso up so that the walker is in the middle of the picture
    base = camera_sphere(model, cam)
    zoom = base * [0.8, 1, 1, 1]
    roll = base + [0, 0, 0, np.pi / 2]
    spheres = np.stack([base, zoom, roll]).astype(np.float32)
    qpos3 = np.repeat(qpos, 3, axis=0)
    _, labels0 = tile_render(model, qpos3[:1], cam, agent, floor, settings)
    _, labels = tile_render(
        model, qpos3, cam, agent, floor, settings, perturb={"cam_sphere": spheres}
    )
    mask0 = labels0[0] == LABEL_AGENT
    same, zoomed, rolled = labels == LABEL_AGENT
    assert (same != mask0).mean() < 0.002  # float rounding of the rebuilt frame only
    ratio = zoomed.sum() / mask0.sum()
    assert 1.3 < ratio < 1.9, ratio  # 1/0.8^2 = 1.56 for a flat object; perspective varies it
    # A quarter turn of the camera turns the picture by a quarter turn (the walker is centred).
    overlap = (np.rot90(mask0, k=1) & rolled).sum() + (np.rot90(mask0, k=-1) & rolled).sum()
    assert overlap / mask0.sum() > 0.6
    assert (rolled & mask0).sum() / mask0.sum() < 0.6


def test_bad_input_is_named():
    model, agent, floor, cam = task_facts("walker")
    with pytest.raises(ValueError, match="both agent and floor"):
        label_tables(model, [0, 1], [0])
    with model_pool(model, agent, floor, cam, R.RenderSettings(num_workers=1)) as pool:
        with pytest.raises(ValueError, match=r"unknown perturbation keys \['colour'\]; valid:"):
            pool.render(model.qpos0[None], perturb={"colour": np.zeros((1, 3))})
        with pytest.raises(ValueError, match=r"\[B, nq\]"):
            pool.render(model.qpos0)
        with pytest.raises(ValueError, match=r"label_rows must be \[B\] = \[1\], got \(2,\)"):
            pool.render(model.qpos0[None], label_rows=np.ones(2, bool))
        info = pool.gl_info()
        assert len(info) == 1 and info[0]["GL_RENDERER"]
        assert info[0]["MUJOCO_EGL_DEVICE_ID"] == os.environ.get("MUJOCO_EGL_DEVICE_ID", "")
        frame = pool.render(model.qpos0[None])
    # A worker told its GPU makes its context there and draws the same picture.
    with model_pool(model, agent, floor, cam, R.RenderSettings(num_workers=1, gpus="0")) as pool:
        assert pool.gl_info()[0]["MUJOCO_EGL_DEVICE_ID"] == "0"
        for a, b in zip(pool.render(model.qpos0[None]), frame, strict=True):
            np.testing.assert_array_equal(a, b)


def test_drawn_on_the_cpu_by_mesa_whatever_the_gpus(monkeypatch):
    """gpus "cpu": each worker makes MuJoCo's EGL display on Mesa's software device (llvmpipe).
    Where that is the default device too (a machine without GPUs), the frames and labels are the
    default pool's bit for bit; beside a GPU's, within a level. Without Mesa's device, or after
    the process made its display, it says what is wrong."""
    import mujoco.egl

    model, agent, floor, cam = task_facts("walker")
    qpos = random_qpos(model, 3, seed=2, scale=0.3)
    with model_pool(model, agent, floor, cam, R.RenderSettings(num_workers=1)) as pool:
        expected = pool.render(qpos)
        default_renderer = pool.gl_info()[0]["GL_RENDERER"]
    with model_pool(model, agent, floor, cam, R.RenderSettings(num_workers=2, gpus="cpu")) as pool:
        assert pool.num_workers == 2
        assert all("llvmpipe" in info["GL_RENDERER"] for info in pool.gl_info())
        rgb, labels = pool.render(qpos)
    if "llvmpipe" in default_renderer:
        np.testing.assert_array_equal(rgb, expected[0])
        np.testing.assert_array_equal(labels, expected[1])
    else:  # an H200's: 0.94 levels, 9 label pixels of 4 x 84 x 84 (benchmarks/RESULTS.md)
        assert np.abs(rgb.astype(int) - expected[0]).mean() < 2.0
        assert (labels != expected[1]).sum() <= 20

    monkeypatch.setenv("LP_NUM_THREADS", "0")
    monkeypatch.setattr(mujoco.egl, "EGL_DISPLAY", None)
    monkeypatch.setattr(mujoco.egl.egl_ext, "eglQueryDevicesEXT", lambda max_devices: [])
    with pytest.raises(RuntimeError, match=r"none of the 0 EGL devices is Mesa's.*libegl-mesa0"):
        R.use_cpu_drawing()
    monkeypatch.setattr(mujoco.egl, "EGL_DISPLAY", object())
    with pytest.raises(RuntimeError, match="has an EGL display already"):
        R.use_cpu_drawing()
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    with pytest.raises(RuntimeError, match="through EGL, but MUJOCO_GL='osmesa'"):
        R.use_cpu_drawing()


def test_workers_draw_on_the_gpus_named_each_on_its_block_of_the_batch():
    """Worker i of W draws on gpus[i * G // W]: the GPU whose lanes own the start of its block."""
    assert R.RenderSettings(gpus="0,1").worker_gpus(8) == [0, 0, 0, 0, 1, 1, 1, 1]
    assert R.RenderSettings(gpus="0,1").worker_gpus(3) == [0, 0, 1]
    assert R.RenderSettings(gpus="3,1,2").worker_gpus(2) == [3, 1]
    assert R.RenderSettings(gpus="1").worker_gpus(2) == [1, 1]
    assert R.RenderSettings().worker_gpus(2) == [None, None]  # MuJoCo's choice
    assert R.RenderSettings(gpus="cpu").worker_gpus(3) == ["cpu"] * 3
    for bad in ("gpu1", "0,", "-1", ""):
        with pytest.raises(ValueError, match="'auto', 'cpu' or GPU numbers separated by commas"):
            R.RenderSettings(gpus=bad)


def test_auto_draws_on_idle_gpus_else_the_lanes_and_numbers_are_checked(monkeypatch):
    """env.render.gpus "auto": a training env's frames on the GPUs its lanes leave idle (as
    many as the lanes' devices at most), where the process has any, else on the GPU numbers of
    the devices the lanes live on, in their order; left to MuJoCo off GPUs, on the first GPU
    alone, or where MUJOCO_EGL_DEVICE_ID is set. make_env hands the env what it resolves to.
    Numbers given are checked against the GPUs the training process sees."""
    from types import SimpleNamespace

    from dear_jax import experiment

    gpus = [SimpleNamespace(platform="gpu", local_hardware_id=i) for i in range(4)]
    cpu = [SimpleNamespace(platform="cpu", local_hardware_id=0)]
    assert experiment.drawing_devices(gpus[:1], gpus) == [gpus[1]]
    assert experiment.drawing_devices(gpus[:2], gpus) == gpus[2:]
    assert experiment.drawing_devices(gpus[:3], gpus) == [gpus[3]]
    assert experiment.drawing_devices(gpus, gpus) == gpus  # none idle: the lanes' own
    assert experiment.drawing_devices(cpu, cpu) == cpu
    monkeypatch.delenv("MUJOCO_EGL_DEVICE_ID", raising=False)
    drawn_on = []
    monkeypatch.setattr(experiment.envs, "make", lambda *a, render, **k: drawn_on.append(render))
    for visible, expected in [(gpus[:2], "1"), (gpus[:1], "auto"), (cpu, "auto")]:
        monkeypatch.setattr(experiment.jax, "local_devices", lambda v=visible: v)
        experiment.make_env(smoke_config.get_config(), envs_per_seed=1, split="train", seed=0)
        assert drawn_on.pop().gpus == expected
    gpus = gpus[:2]
    assert experiment.render_gpus("auto", gpus[::-1]) == "1,0"
    assert experiment.render_gpus("auto", gpus[1:]) == "1"  # an evaluation's spare GPU
    assert experiment.render_gpus("auto", gpus[:1]) == "auto"  # the first GPU: MuJoCo's choice
    assert experiment.render_gpus("auto", [SimpleNamespace(platform="cpu")]) == "auto"
    assert experiment.render_gpus("1", gpus[:1]) == "1"
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "1")
    assert experiment.render_gpus("auto", gpus) == "auto"

    config = smoke_config.get_config()
    monkeypatch.setattr(experiment.jax, "local_devices", lambda: gpus)
    for setting, message in [
        ("0,2", r"env.render.gpus='0,2': this process sees 2 GPU\(s\) \(0-1\); valid: 'auto'"),
        ("gpu1", r"env.render: render gpus 'gpu1': 'auto', 'cpu' or GPU numbers separated by"),
    ]:
        config.env.render.gpus = setting
        with pytest.raises(ValueError, match=message):
            experiment.validate(config)
    config.env.render.gpus = "1"
    experiment.validate(config)
    monkeypatch.setattr(experiment.jax, "local_devices", lambda: [])
    with pytest.raises(ValueError, match=r"sees 0 GPU\(s\); valid: 'auto', 'cpu' or GPU numbers"):
        experiment.validate(config)
    config.env.render.gpus = "cpu"  # no GPU needed
    experiment.validate(config)


def test_a_worker_without_an_offscreen_buffer_names_the_setting_to_lower():
    from envs.render_pool import _hint

    error = "mujoco.FatalError: Offscreen framebuffer is not complete, error 0x8cdd"
    assert "env.render.num_workers" in _hint(error, 8) and "8 render workers" in _hint(error, 8)
    assert _hint("ValueError: camera 'x' not in the model", 8) == ""
