"""Preview a task before training: a PNG grid of RGB frames above their agent masks.

    python -m envs.preview walker-walk --out preview.png [--distraction medium] \
        [--distraction-types background|all] [--mask noisy|approximate] \
        [--background-dir DAVIS_ROOT] [--dynamic]

Runs a few envs for a few random-action steps through `envs.make` (the same path training uses:
physics, render pool, distraction compositing, mask variant) with the pictures, physics backend
and action repeat a run of the task has by default (`run_settings`: the kitchen's from
configs/kitchen.py, the others' from configs/base.py), and writes, per env, one row of frames
and below it one row of the training mask (white = agent) of the same frames.
"""

from __future__ import annotations

import argparse
import logging
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402


def collect(env, num_frames: int, every: int, seed: int):
    """-> frames uint8 [E, F, H, W, 3], masks uint8 [E, F, H, W], step numbers [F]."""
    import jax

    key = jax.random.key(seed)
    key, reset_key = jax.random.split(key)
    state, ts = env.reset(reset_key)
    frames, masks, steps = [np.asarray(ts.frame[0])], [np.asarray(ts.mask[0])], [0]
    shape = (*env.shape, env.spec.action_dim)
    for t in range(1, (num_frames - 1) * every + 1):
        key, act_key = jax.random.split(key)
        action = jax.random.uniform(act_key, shape, minval=-1.0, maxval=1.0)
        state, ts = env.step(state, action)
        if t % every == 0:
            frames.append(np.asarray(ts.frame[0]))
            masks.append(np.asarray(ts.mask[0]))
            steps.append(t)
    return np.stack(frames, axis=1), np.stack(masks, axis=1), steps


def run_settings(task: str):
    """The env settings a run of `task` starts from: configs/paper.py's for the kitchen's tasks
    (its pictures, CPU physics, action repeat 1), configs/base.py's for the others."""
    from dear_jax.config import load_config

    if task.startswith("kitchen-"):
        return load_config(f"paper.py:{task.removeprefix('kitchen-')},dear").env
    return load_config("base.py").env


def grid_image(frames: np.ndarray, masks: np.ndarray, scale: int = 2, gap: int = 2) -> np.ndarray:
    """frames [E,F,H,W,3], masks [E,F,H,W] -> one uint8 image: per env an RGB row, a mask row."""
    e, f, h, w, _ = frames.shape
    rows = []
    for i in range(e):
        rows.append(frames[i])
        rows.append(np.repeat(masks[i][..., None] * 255, 3, axis=-1).astype(np.uint8))
    th, tw = h * scale + gap, w * scale + gap
    out = np.full((len(rows) * th + gap, f * tw + gap, 3), 64, np.uint8)
    for r, row in enumerate(rows):
        for c in range(f):
            tile = np.repeat(np.repeat(row[c], scale, axis=0), scale, axis=1)
            out[
                gap + r * th : gap + r * th + h * scale, gap + c * tw : gap + c * tw + w * scale
            ] = tile
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m envs.preview", description="Write a PNG grid of frames and agent masks."
    )
    parser.add_argument("task", help="registry name, e.g. walker-walk")
    parser.add_argument("--out", required=True, help="PNG file to write")
    parser.add_argument(
        "--distraction",
        default="none",
        help="none | easy | medium | hard; with -full (medium-full), the full suite's types",
    )
    parser.add_argument(
        "--distraction-types",
        default="background",
        help="background (the paper's setting, as configs/paper.py's DIFFICULTY), all (the full "
        "suite: background, color, camera), or a comma-separated subset",
    )
    parser.add_argument("--dynamic", action="store_true", help="distractions move in an episode")
    parser.add_argument("--mask", default="true", help="true | noisy | approximate")
    parser.add_argument("--mask-drop-prob", type=float, default=0.8)
    parser.add_argument("--background-dir", default=None, help="DAVIS-2017 root")
    parser.add_argument(
        "--split", default="train", choices=("train", "val"), help="background videos"
    )
    parser.add_argument("--envs", type=int, default=2, help="envs shown (rows)")
    parser.add_argument("--frames", type=int, default=6, help="frames per env (columns)")
    parser.add_argument("--every", type=int, default=5, help="agent steps between columns")
    parser.add_argument("--backend", default=None, help="cpu | mjx | auto; default: a run's")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    # The envs' notes (which background videos, which physics); libraries' only from warnings.
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("envs").setLevel(logging.INFO)

    import cv2

    import envs
    from configs.paper import DIFFICULTIES  # the levels a run's config string takes
    from envs import distractions

    if not cv2.haveImageWriter(args.out):
        parser.error(f"--out {args.out}: OpenCV writes no image of that extension; give a .png")
    for name in ("envs", "frames", "every"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")

    distraction, types = args.distraction, args.distraction_types
    if distraction not in DIFFICULTIES:
        parser.error(f"unknown distraction {distraction!r}; valid: {', '.join(DIFFICULTIES)}")
    if distraction.endswith("-full"):  # configs/paper.py's name of the full suite's level
        distraction, types = distraction.removesuffix("-full"), "all"
    try:  # bad input: one line, as run.py says it
        distractions.parse_types(types)
        if args.task not in envs.names():
            raise ValueError(f"unknown task {args.task!r}; valid tasks: {', '.join(envs.names())}")
        settings = run_settings(args.task)
        env = envs.make(
            args.task,
            num_seeds=1,
            envs_per_seed=args.envs,
            backend=args.backend or settings.backend,
            action_repeat=settings.action_repeat,
            render=envs.RenderSettings(**settings.render.to_dict()),
            distraction=distraction,
            distraction_types=types,
            dynamic=args.dynamic,
            background_dir=args.background_dir,
            split=args.split,
            mask=args.mask,
            mask_drop_prob=args.mask_drop_prob,
            seed=args.seed,
        )
    except (ValueError, FileNotFoundError, NotADirectoryError) as e:
        parser.error(str(e))
    with env:
        frames, masks, steps = collect(env, args.frames, args.every, args.seed)
    image = grid_image(frames, masks)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    if not cv2.imwrite(args.out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {args.out}")
    print(
        f"wrote {args.out}: {args.envs} envs x {len(steps)} frames (agent steps {steps}); "
        f"per env a row of RGB frames above a row of '{args.mask}' masks"
    )


if __name__ == "__main__":
    main()
