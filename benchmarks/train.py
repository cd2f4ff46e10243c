"""End-to-end training throughput, and where an iteration's time goes.

    python -m benchmarks.train --config configs/walker_dear.py --seeds 5 --envs 8 --frames 20000

1. Throughput: the real `dear_jax.train.train` loop (rendering overlapped with updates) runs
   `--warmup-frames` + `--frames` frames per seed; aggregate env frames/s is read from its train
   log over the intervals after warm-up (updates compiled and running).
2. Split: the stages of one iteration timed one by one, each synchronised (so their sum is what
   the loop would cost without overlap): physics (dispatch + compute), physics-state transfer to
   the host, render (RGB + labels), upload + compositing/masks/stack, the E/update_every updates
   per seed, and acting + replay insertion ("other").
Prints tables and writes JSON to benchmarks/results/train_<device>.json (or --out). The frames are
drawn on the GPUs that train, as a machine of only those draws them (`drawn_beside_lanes`), unless
`--set env.render.gpus=...` says where (`--vary env.render.gpus 0 1`: on a second GPU or not).

`--label-pass off`: the training env draws no segmentation pass (its masks all 0), a diagnostic of
what that pass costs the loop where it is drawn; never a run's setting.

`--vary KEY V1 V2 ...` (repeatable) measures the throughput of every combination of the values
in one process, in turn `--rounds` times, every other round in reverse (an A/B on the same
machine state; programs compile once where only env fields vary), e.g. `--vary
env.physics_threads 1 4 --vary env.switch_interval_ms 0 0.1`.
The PyTorch pipeline of the reference's shape: `python -m benchmarks.torch_reference pipeline`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import itertools
import logging
import os
import pathlib
import tempfile
import time
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import save_json
from dear_jax import experiment, replay, summary, train, update
from dear_jax.config import check_override_keys, load_config
from dear_jax.logger import format_table, read_csv
from dear_jax.programs import build_programs
from dear_jax.signals import Stopped

PYTORCH_ANCHOR_FPS = (
    262.0  # docs/design.md: PyTorch pipeline of the reference's shape, 5 processes, H100
)


def bench_config(args):
    c = load_config(args.config)  # e.g. configs/paper.py:walker,dear
    c.seeds, c.envs_per_seed = args.seeds, args.envs
    c.replay.seed_frames = args.warmup_frames // 2
    c.total_frames = args.warmup_frames + args.frames
    c.log_every_frames = args.log_every
    c.eval_every_frames = args.eval_every or 10**9  # 0: only the closing evaluation
    c.num_eval_episodes = args.eval_episodes if args.eval_every else 1
    c.eval_in_background = not args.eval_foreground
    c.env.episode_frames = 0
    c.checkpoint_every_frames = 0
    c.save_video = False
    c.progress = False
    c.replay.capacity = min(c.replay.capacity, args.capacity)
    c.agent.compute_dtype = args.dtype
    c.env.backend = args.backend or c.env.backend
    for item in args.set:
        set_field(c, item)
    return c


def set_field(config, item: str) -> None:
    """Apply one `KEY=VALUE` (dotted key, e.g. agent.shift_impl=gather), typed as the field is."""
    if "=" not in item:
        raise ValueError(f"--set takes KEY=VALUE, got {item!r}")
    dotted, value = item.split("=", 1)
    check_override_keys(config, [f"--config.{dotted}"])
    *parents, name = dotted.split(".")
    node = config
    for part in parents:
        node = node[part]
    old = node[name]
    if isinstance(old, bool):
        if value not in ("True", "False", "true", "false"):
            raise ValueError(f"{dotted} is a bool: give true or false, got {value!r}")
        node[name] = value in ("True", "true")
    else:
        node[name] = type(old)(value)


def variants(vary: list[list[str]]) -> list[list[str]]:
    """[[KEY, V1, V2, ...], ...] -> every combination as `--set` items, the last key fastest."""
    axes = []
    for key, *values in vary:
        if not values:
            raise ValueError(f"--vary takes a KEY and its values, got only {key!r}")
        axes.append([f"{key}={v}" for v in values])
    return [list(c) for c in itertools.product(*axes)]


def drawn_beside_lanes(config):
    """`config` with env.render.gpus "auto" made the GPUs that train its lanes (the first
    `config.devices`) where the process sees more GPUs than those: "auto" would draw on one the
    run leaves idle (experiment.drawing_devices), and a figure would depend on how many GPUs the
    machine has. Numbers given, CPU devices and a set MUJOCO_EGL_DEVICE_ID stay as they are."""
    local = [d for d in jax.local_devices() if d.platform == "gpu"]
    used = len(local) if config.devices == "all" else int(config.devices)
    if (
        config.env.render.gpus != "auto"
        or used >= len(local)
        or os.environ.get("MUJOCO_EGL_DEVICE_ID")
    ):
        return config
    config = copy.deepcopy(config)
    config.env.render.gpus = ",".join(str(d.local_hardware_id) for d in local[:used])
    return config


@contextlib.contextmanager
def label_pass(setting: str):
    """Within it, `train.train`'s env draws the segmentation pass where the method reads masks
    ("auto") or nowhere ("off": `experiment.make_env(labels=False)`, masks all 0)."""
    if setting == "auto":
        yield
        return
    without = functools.partial(experiment.make_env, labels=False)
    with mock.patch.object(train, "make_env", without):
        yield


def throughput(config, warmup_frames, labels: str = "auto") -> dict:
    config = drawn_beside_lanes(config)
    with tempfile.TemporaryDirectory() as workdir, label_pass(labels):
        t0 = time.perf_counter()
        try:
            updates = train.train(config, workdir)["updates_per_seed"]
        except Stopped as e:  # cut short (a time limit's SIGTERM): the rows so far still count
            print(e)
            updates = None
        total_s = time.perf_counter() - t0
        logs = read_csv(pathlib.Path(workdir) / "seed_0" / "train.csv")
        eval_csv = pathlib.Path(workdir) / "seed_0" / "eval.csv"  # absent if none finished
        evals = read_csv(eval_csv) if eval_csv.is_file() else {"eval_s": np.array([])}
    frames, fps = logs["frame"], logs["fps"]
    after = frames > warmup_frames + config.log_every_frames  # skip the interval with the compile
    # Each row's rate covers the frames since the row before; evaluations (in the background, or
    # holding up the loop) fall inside those intervals. Over the measured span: frames / time.
    span = np.diff(frames, prepend=0)[after] * config.seeds
    span_fps = float(span.sum() / (span / fps[after]).sum()) if after.any() else float("nan")
    return dict(
        # The loop's own account of an iteration (dear_jax.loop.Loop.host_seconds), ms.
        host_ms_per_iteration=summary.stage_means(logs, after),
        aggregate_fps=float(np.mean(fps[after])) if after.any() else float("nan"),
        median_row_fps=float(np.median(fps[after])) if after.any() else float("nan"),
        span_fps_with_evaluations=span_fps,
        fps_rows=fps[after].tolist(),
        eval_s=evals["eval_s"].tolist(),  # seconds each evaluation took (frame 0's first)
        total_s=total_s,
        updates_per_seed=updates,
    )


def _timed(fn, reps):
    out = fn()
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn()
        jax.block_until_ready(out)
    return (time.perf_counter() - t0) / reps * 1e3, out


def stage_split(config, reps) -> dict:
    """Milliseconds per loop iteration, each stage synchronised on its own."""
    config = drawn_beside_lanes(config)
    num_seeds, num_envs = config.seeds, config.envs_per_seed
    env = experiment.make_env(config, envs_per_seed=num_envs, split="train", seed=0)
    try:
        spec = env.spec
        acfg = experiment.agent_config(config, spec.action_dim)
        hp = experiment.hparams(config)
        programs = build_programs(acfg, hp, config)
        agent = jax.jit(functools.partial(update.init_seeds, acfg))(
            jax.random.split(jax.random.key(0), num_seeds)
        )
        buffer = replay.init(
            config.replay.capacity,
            num_envs,
            spec.frame_shape,
            spec.action_dim,
            leading=(num_seeds,),
        )
        state, ts = env.reset(jax.random.key(1))
        # Uniform actions, as exploration takes them: the physics' cost depends on the poses
        # the actions lead to (a zero action lets the kitchen's arm sag onto the counter).
        rng = np.random.default_rng(0)
        shape = (num_seeds, num_envs, spec.action_dim)
        action = jnp.asarray(rng.uniform(-1.0, 1.0, shape), jnp.float32)
        buffer = programs.add(buffer, ts, action)
        for _ in range(8):  # a few rows so that sampling has transitions
            state, ts = env.step(state, action)
            buffer = programs.add(buffer, ts, action)
        n_updates = max(1, num_envs // config.agent.update_every_steps)
        # as the loop hands them: [per_call] keys a call
        per_call = experiment.updates_per_call(config)
        if n_updates % per_call:
            raise ValueError(f"agent.updates_per_call={per_call} does not divide {n_updates}")
        key = jax.random.key(2)
        ms = {}
        ms["physics"], (phys, _) = _timed(lambda: env.physics.step(state.physics, action), reps)
        ms["transfer to host"], qpos = _timed(
            lambda: np.asarray(env.physics.qpos(phys)).reshape(env.batch, -1), reps
        )
        perturb = env._distractor.perturb()
        ms["render"], _ = _timed(lambda: env._pool.render(qpos, perturb=perturb), reps)
        env_ms, _ = _timed(lambda: env.step(state, action)[1], reps)
        ms["upload + composite + masks"] = max(
            env_ms - ms["physics"] - ms["transfer to host"] - ms["render"], 0.0
        )
        # The loop's programs donate their first argument: thread it through the repetitions.
        held = {"agent": agent, "buffer": buffer}

        def learn():
            keys = jax.random.split(key, n_updates)
            for k in keys.reshape(-1, per_call) if per_call > 1 else keys:
                held["agent"], metrics = programs.learn(held["agent"], held["buffer"], k)
            return metrics

        def act():
            out, held["agent"] = programs.act(held["agent"], ts.obs, key, ~np.asarray(state.last))
            return out

        def add():
            held["buffer"] = programs.add(held["buffer"], ts, action)
            return held["buffer"].pos

        ms["update"], _ = _timed(learn, reps)
        ms["other (act + replay add)"] = _timed(act, reps)[0] + _timed(add, reps)[0]
        return dict(
            ms=ms,
            n_updates=n_updates,
            frames_per_iteration=num_seeds * num_envs * spec.action_repeat,
        )
    finally:
        env.close()


def add_run_arguments(p: argparse.ArgumentParser, seeds: int = 5) -> None:
    """The flags `bench_config` reads (also benchmarks/scaling.py's)."""
    p.add_argument("--config", default="configs/walker_dear.py")
    p.add_argument("--seeds", type=int, default=seeds)
    p.add_argument("--envs", type=int, default=8)
    p.add_argument("--frames", type=int, default=20_000, help="measured frames per seed")
    p.add_argument("--warmup-frames", type=int, default=4000)
    p.add_argument("--log-every", type=int, default=2000)
    p.add_argument("--capacity", type=int, default=100_000)
    p.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    p.add_argument(
        "--backend", choices=["auto", "mjx", "cpu"], help="physics (default: the config's)"
    )
    p.add_argument("--eval-every", type=int, default=0, help="frames per seed; 0: at the end")
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--eval-foreground", action="store_true", help="training waits for evals")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other config field, e.g. --set agent.shift_impl=gather (repeatable)",
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    add_run_arguments(p)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--skip", nargs="*", default=[], choices=["throughput", "split"])
    p.add_argument(
        "--vary",
        action="append",
        nargs="+",
        default=[],
        metavar="KEY V1",
        help="a field and its values: the throughput of each combination (repeatable)",
    )
    p.add_argument("--rounds", type=int, default=1, help="with --vary: combinations in turn")
    p.add_argument(
        "--label-pass",
        choices=["auto", "off"],
        default="auto",
        help="off: the training env draws no segmentation pass (a diagnostic; masks all 0)",
    )
    p.add_argument("--out", default=None)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    config = bench_config(args)
    combinations = variants(args.vary)
    for item in dict.fromkeys(itertools.chain(*combinations)):  # refused before any stage runs
        set_field(bench_config(args), item)
    device = jax.devices()[0]
    result = dict(
        device=device.device_kind,
        platform=device.platform,
        config=args.config,
        seeds=args.seeds,
        envs_per_seed=args.envs,
        dtype=args.dtype,
        seed_axis=config.agent.seed_axis,
        batch_size=config.agent.batch_size,
        method=config.agent.method,
        task=config.env.task,
        label_pass=args.label_pass,
    )

    def save():  # after every stage, so a run cut off in the next stage keeps this one
        save_json(result, args.out, f"benchmarks/results/train_{device.platform}.json")

    if "split" not in args.skip:
        split = stage_split(config, args.reps)
        result["split"] = split
        total = sum(split["ms"].values())
        rows = [[k, f"{v:.1f}", f"{100 * v / total:.0f}%"] for k, v in split["ms"].items()]
        rows.append(
            [
                "sum (no overlap)",
                f"{total:.1f}",
                f"{split['frames_per_iteration'] / total * 1e3:.0f} frames/s",
            ]
        )
        print(
            f"\nOne iteration: {args.seeds} seeds x {args.envs} envs, "
            f"{split['n_updates']} updates per seed ({device.device_kind})"
        )
        print(format_table(["stage", "ms", "share"], rows))
        save()
    if args.vary:
        result["variants"] = []
        rows = []
        # Every other round in reverse (A B C, C B A, ...): a drift of the machine over the
        # rounds then weighs on every combination alike.
        todo = [
            (r, config_set)
            for r in range(args.rounds)
            for config_set in (combinations if r % 2 == 0 else combinations[::-1])
        ]
        for round_, config_set in todo:
            varied = bench_config(args)
            for item in config_set:
                set_field(varied, item)
            tp = throughput(varied, args.warmup_frames, args.label_pass)
            result["variants"].append(dict(set=config_set, round=round_, **tp))
            rows.append([" ".join(config_set), round_, f"{tp['aggregate_fps']:.0f}"])
            save()
            if tp["updates_per_seed"] is None:  # a signal stopped it: so it stops the rest
                print(f"stopped: {len(todo) - len(rows)} setting(s) not measured")
                break
        print(f"\nEnd to end ({device.device_kind}), env frames/s in all:")
        print(format_table(["setting", "round", "frames/s"], rows))
    elif "throughput" not in args.skip:
        tp = throughput(config, args.warmup_frames, args.label_pass)
        result["throughput"] = tp
        print(
            f"\nEnd to end ({device.device_kind}): {tp['aggregate_fps']:.0f} env frames/s in all "
            f"({args.seeds} seeds x {args.envs} envs, {config.agent.method}, "
            f"{config.env.task}); {tp['aggregate_fps'] / PYTORCH_ANCHOR_FPS:.1f}x the PyTorch "
            f"pipeline's {PYTORCH_ANCHOR_FPS:.0f} frames/s (docs/design.md)"
        )
        print(
            "per iteration, ms (the loop's log): "
            + ", ".join(f"{k} {v:.1f}" for k, v in tp["host_ms_per_iteration"].items())
        )
        if args.eval_every:
            print(
                f"evaluating {config.num_eval_episodes} episodes per seed every "
                f"{args.eval_every} frames ({'foreground' if args.eval_foreground else 'background'}"
                f", {config.env.eval_backend} physics): {tp['span_fps_with_evaluations']:.0f} "
                f"frames/s over the measured span against a median row of "
                f"{tp['median_row_fps']:.0f}: x{tp['median_row_fps'] / tp['span_fps_with_evaluations']:.2f}"
            )
        save()


if __name__ == "__main__":
    main()
