"""What a config makes of an experiment: the fields that change what it learns (its
checkpoint's fingerprint), its checks, its agent's settings, its envs, where it evaluates and
its replay's store on disk.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import pathlib

import jax
import jax.numpy as jnp
from jax.sharding import Mesh
from ml_collections import ConfigDict

import envs
from dear_jax import augment, lanes, losses, networks, replay, replay_disk, update, wideconv
from dear_jax.devices import Hosts, lanes_per_host, num_devices
from envs import distractions, render

log = logging.getLogger("dear_jax")

# Fields since removed that never changed what a run learns: the config.json of runs made
# before still names them, and a resume or a comparison of configs passes over them.
REMOVED_FIELDS = ("env.render.as_stepped",)

# Config fields a resumed run may change: how long it runs, what and how often it logs, evaluates
# and saves, and how fast it runs; never what it learns. Every other field, new ones included, is
# part of the checkpoint's fingerprint, and a resume that changes one is refused.
RESUMABLE_CHANGES = (
    "total_frames",
    "eval_every_frames",
    "num_eval_episodes",
    "log_every_frames",
    "checkpoint_every_frames",
    "keep_checkpoints",
    "save_video",
    "progress",
    "profile.at_frame",
    "profile.iterations",
    "env.render.num_workers",
    "env.render.envs_per_worker",
    "env.render.gpus",
    "env.eval_backend",
    "env.physics_threads",
    "env.eval_physics_threads",
    "env.switch_interval_ms",
    "eval_in_background",
    "eval_device",
    "eval_processes",
    "eval_nice",
    "agent.seed_axis",
    "agent.shift_impl",
    "agent.filter_gradient",
    "agent.conv_stack",
    "agent.kernels",
    "agent.updates_per_call",
    "agent.xla_options",
    "replay.disk",
    "devices",
    "devices_per_seed",
    *REMOVED_FIELDS,
)


# Fields added to the config after runs were made, each with the value that does what the code
# did before it: a checkpoint written without the field resumes when the config has that value.
ADDED_FIELDS = {
    "env.distraction_types": "all",
    "env.render.mesh_faces": 0,
    "env.render.num_slices": 0,
    "env.render.num_stacks": 0,
    "replay.sampling": "uniform",
    "agent.noise_hold": 1,
    "agent.ted_form": "strict",
    "sweep.noise_hold": "",
}


def fingerprint(config: ConfigDict) -> dict:
    """Every config field that changes what a run learns (all but RESUMABLE_CHANGES), dotted."""
    return {k: v for k, v in lanes.flatten(config.to_dict()).items() if k not in RESUMABLE_CHANGES}


# Offset of process p's env seeds (and episode-start keys): p * HOST_SEED_STRIDE.
HOST_SEED_STRIDE = 1_000_033
# Offset of evaluation process i's eval-env seed (`eval_processes`): i * EVAL_STREAM_STRIDE.
EVAL_STREAM_STRIDE = 1_000_037

EVAL_DEVICES = ("auto", "cpu", "accelerator", "train")
OWN_PROCESS = ("cpu", "accelerator")  # eval_device values that evaluate in a child process
# Evaluation processes where config.eval_processes is 0 and they run in processes of their own
# beside a training on a GPU: with one, a lone seed's loop on the paper's grid waited up to 21%
# of its run for evaluations (benchmarks/RESULTS.md, "Evaluation"). On a CPU-only machine a
# second would take the training's cores.
AUTO_EVAL_PROCESSES = 2


def _get(config: ConfigDict, dotted: str):
    for part in dotted.split("."):
        config = config[part]
    return config


class ConfigError(ValueError):
    """Bad input found once the run has its envs and devices (`validate` finds the rest):
    run.py prints its message as one line."""


def validate(config: ConfigDict) -> None:
    """Fail early, naming the field and the valid choices."""
    if config.env.task not in envs.names():
        raise ValueError(f"unknown env.task {config.env.task!r}; valid: {', '.join(envs.names())}")
    choices = {
        "agent.method": update.METHODS,
        "agent.encoder": ("pool", "plain"),
        "agent.ortho_form": losses.ORTHOGONALITY_FORMS,
        "agent.ted_form": losses.TED_FORMS,
        "agent.seed_axis": update.SEED_AXES,
        "agent.shift_impl": augment.SHIFT_IMPLS,
        "agent.filter_gradient": networks.FILTER_GRADIENTS,
        "agent.conv_stack": networks.STACKS,
        "env.backend": ("auto", "mjx", "cpu"),
        "env.eval_backend": ("cpu", "train"),
        "eval_device": EVAL_DEVICES,
        "env.distraction": ("none", "easy", "medium", "hard"),
        "env.mask": ("true", "noisy", "approximate"),
        "env.render.quality": render.QUALITIES,
        "agent.compute_dtype": ("float32", "bfloat16"),
        "replay.sampling": replay.SAMPLINGS,
    }
    for key, valid in choices.items():
        if _get(config, key) not in valid:
            raise ValueError(f"unknown {key} {_get(config, key)!r}; valid: {', '.join(valid)}")
    if not (isinstance(config.eval_processes, int) and config.eval_processes >= 0):
        raise ValueError(
            f"eval_processes must be an int >= 1, or 0 (two on a GPU machine, else one); got "
            f"{config.eval_processes!r}"
        )
    if config.eval_device != "auto":  # "auto" is checked once resolved (eval_device)
        _check_eval_processes(config, config.eval_device, multi=False)
    if not (isinstance(config.eval_nice, int) and 0 <= config.eval_nice <= 19):
        raise ValueError(
            f"eval_nice must be an int in 0-19 (0: the training's), got {config.eval_nice!r}"
        )
    try:
        distractions.parse_types(config.env.distraction_types)
    except ValueError as e:
        raise ValueError(f"env.distraction_types: {e}") from None
    try:
        render.RenderSettings(**config.env.render.to_dict())
    except (TypeError, ValueError) as e:
        raise ValueError(f"env.render: {e}") from None
    gpus = config.env.render.gpus
    if gpus not in ("auto", render.CPU):
        seen = len([d for d in jax.local_devices() if d.platform == "gpu"])
        if any(int(g) >= seen for g in gpus.split(",")):
            visible = f" (0-{seen - 1})" if seen else ""
            raise ValueError(
                f"env.render.gpus={gpus!r}: this process sees {seen} GPU(s){visible}; valid: "
                "'auto', 'cpu' or GPU numbers it sees"
            )
    try:
        wideconv.parse_constants(config.agent.kernels)
    except ValueError as e:
        raise ValueError(f"agent.kernels: {e}") from None
    try:
        agent_config(config, action_dim=1)  # the agent's fields together (method x encoder)
    except ValueError as e:
        raise ValueError(f"agent: {e}") from None
    if config.agent.kernels and networks.stack_for(config.agent.conv_stack) != "pallas":
        log.warning(
            "agent.kernels=%r sets the Pallas stacks' constants, but the conv stacks run in XLA "
            "here (agent.conv_stack=%r): it changes nothing",
            config.agent.kernels,
            config.agent.conv_stack,
        )
    positive = (
        "seeds",
        "devices_per_seed",
        "envs_per_seed",
        "total_frames",
        "eval_every_frames",
        "num_eval_episodes",
        "agent.batch_size",
        "agent.nstep",
        "agent.update_every_steps",
        "agent.latent_dim",
        "agent.feature_dim",
        "agent.hidden_dim",
        "replay.capacity",
        "env.action_repeat",
        "log_every_frames",
        "keep_checkpoints",
        "replay.chunk_entries",
    )
    for key in positive:
        if _get(config, key) < 1:
            raise ValueError(f"{key} must be >= 1, got {_get(config, key)}")
    if not (isinstance(config.agent.updates_per_call, int) and config.agent.updates_per_call >= 0):
        raise ValueError(
            "agent.updates_per_call must be an int >= 1, or 0 (on a GPU an iteration's updates, "
            f"else 1); got {config.agent.updates_per_call!r}"
        )
    try:  # XLA names an unknown option or a bad value as the program compiles
        jax.jit(lambda: 0, compiler_options=xla_options(config.agent.xla_options)).lower().compile()
    except Exception as e:  # noqa: BLE001 - XLA's own errors, whatever their type
        raise ValueError(f"agent.xla_options={config.agent.xla_options!r}: {e}") from None
    for key, low, high in [  # (low, high]: an interval open at its left end, or [0, 1]
        ("agent.lr", 0.0, math.inf),
        ("agent.ted_lr", 0.0, math.inf),
        ("agent.discount", 0.0, 1.0),
    ]:
        if not low < _get(config, key) <= high:
            raise ValueError(f"{key} must be in ({low:g}, {high:g}], got {_get(config, key)}")
    e = config.env
    if not 0.0 <= e.mask_drop_prob <= 1.0:
        raise ValueError(f"env.mask_drop_prob must be in [0, 1], got {e.mask_drop_prob}")
    for key in lanes.SWEEPABLE:  # the update's per-lane numbers, as a sweep's are checked
        try:
            lanes.check_value(key, _get(config, f"agent.{key}"))
        except ValueError as e:
            raise ValueError(f"agent.{e}") from None
    if e.episode_frames < 0:
        raise ValueError(
            f"env.episode_frames must be >= 0 (0: the task's own), got {e.episode_frames}"
        )
    frames = e.episode_frames or envs.frames_per_episode(e.task)
    if frames % e.action_repeat:
        whose = "env.episode_frames" if e.episode_frames else f"{e.task}'s episode"
        raise ValueError(
            f"env.action_repeat={e.action_repeat} does not divide {whose} of {frames} frames; "
            f"give a divisor of {frames}"
        )
    for key, auto in [
        ("env.physics_threads", "one per device"),
        ("env.eval_physics_threads", "one per core, up to 8"),
        ("env.switch_interval_ms", "Python's own"),
        ("checkpoint_every_frames", "no periodic checkpoints"),
    ]:
        if _get(config, key) < 0:
            raise ValueError(f"{key} must be >= 0 (0: {auto}), got {_get(config, key)}")
    a, r = config.agent, config.replay
    steps = r.seed_frames // config.env.action_repeat  # transitions per seed before updating
    if steps < a.batch_size:
        raise ValueError(
            f"replay.seed_frames={r.seed_frames} gives {steps} transitions per seed (at "
            f"env.action_repeat={config.env.action_repeat}) before the first update, fewer than "
            f"one batch (agent.batch_size={a.batch_size}); set replay.seed_frames >= "
            f"{a.batch_size * config.env.action_repeat}"
        )
    if r.seed_frames >= config.total_frames:  # a check of the envs and evaluations, or a slip
        log.warning(
            "replay.seed_frames=%d is not below total_frames=%d: this run collects frames and "
            "never updates the agent; lower replay.seed_frames or raise total_frames to train",
            r.seed_frames,
            config.total_frames,
        )
    if a.encoder == "pool" and a.latent_dim % 2:
        raise ValueError(
            f"agent.latent_dim={a.latent_dim} must be even: the latent splits into halves "
            "(z_E, z_A)"
        )
    if a.batch_size > r.capacity:
        raise ValueError(
            f"agent.batch_size={a.batch_size} is larger than the replay "
            f"(replay.capacity={r.capacity}); lower the batch or raise the capacity"
        )
    stack = update.AgentConfig.frame_stack
    if math.ceil(r.capacity / config.envs_per_seed) <= stack:
        raise ValueError(
            f"replay.capacity={r.capacity} holds {math.ceil(r.capacity / config.envs_per_seed)} "
            f"steps of envs_per_seed={config.envs_per_seed} envs: a transition needs a stack of "
            f"{stack} frames and the step after it; raise replay.capacity above "
            f"{stack * config.envs_per_seed}"
        )
    lanes.sweep_values(config)  # unknown or ineffective sweep keys
    per_host = lanes_per_host(lanes.num_lanes(config), jax.process_count())
    if a.batch_size % config.devices_per_seed:
        raise ValueError(
            f"agent.batch_size={a.batch_size} cannot be split evenly over devices_per_seed="
            f"{config.devices_per_seed} devices; make it a multiple of {config.devices_per_seed}"
        )
    num_devices(config.devices, per_host, jax.local_device_count(), config.devices_per_seed)
    if config.env.background_dir and not pathlib.Path(config.env.background_dir).is_dir():
        raise FileNotFoundError(
            f"env.background_dir {config.env.background_dir!r} is not a folder; give a DAVIS-2017 "
            "root (JPEGImages/480p/<video>/*.jpg, ImageSets/2017/train.txt and val.txt) or '' "
            "for the built-in procedural backgrounds"
        )


def agent_config(config: ConfigDict, action_dim: int) -> update.AgentConfig:
    a = config.agent
    return update.AgentConfig(
        action_dim=action_dim,
        method=a.method,
        encoder=a.encoder,
        latent_dim=a.latent_dim,
        feature_dim=a.feature_dim,
        hidden_dim=a.hidden_dim,
        lr=a.lr,
        ted_lr=a.ted_lr,
        ortho_form=a.ortho_form,
        ted_form=a.ted_form,
        compute_dtype=a.compute_dtype,
        shift_impl=a.shift_impl,
        filter_gradient=a.filter_gradient,
        conv_stack=a.conv_stack,
        kernels=a.kernels,
    )


def hparams(config: ConfigDict) -> update.HParams:
    """The update's per-lane numbers: [lanes] arrays, the config's values and the sweep's."""
    a = config.agent
    runs = lanes.lanes(config)
    names = [f.name for f in dataclasses.fields(update.HParams)]
    return update.HParams(
        **{n: jnp.array([dict(r.settings).get(n, a[n]) for r in runs], jnp.float32) for n in names}
    )


def updates_per_call(config: ConfigDict) -> int:
    """agent.updates_per_call, its 0 ("auto") resolved: on a GPU an iteration's updates
    (envs_per_seed / update_every_steps, at least 1), where dispatching them one call each
    would set the loop's pace; elsewhere 1 (on a CPU a scan of updates compiles ~3x slower)."""
    k = config.agent.updates_per_call
    if k:
        return k
    if jax.default_backend() != "gpu":
        return 1
    return max(1, config.envs_per_seed // config.agent.update_every_steps)


def xla_options(text: str) -> dict[str, str]:
    """agent.xla_options, "NAME=VALUE,...", as jax.jit's compiler_options (XLA's own flags
    without their leading --, e.g. "xla_gpu_command_buffer_scheduling_mode=CONCURRENT")."""
    options = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, _, value = item.partition("=")
        if not name.startswith("xla_") or not value:
            raise ValueError(f"{item!r}: give NAME=VALUE, NAME an XLA option (xla_...)")
        options[name] = value
    return options


def eval_device(config: ConfigDict, hosts: Hosts) -> str:
    """Where the evaluations run (config.eval_device, "auto" resolved): a process of their own
    on the host's CPU ("cpu") or on the training's accelerator ("accelerator";
    dear_jax/evaluator.py), or "train", this process.

    "auto" is "accelerator" for a run of one process on a GPU: on an H100 its evaluations slowed
    training less than "cpu" did (benchmarks/RESULTS.md, "Evaluation");
    "cpu" elsewhere (a CPU-only machine runs the policy in float32); "train" for several
    processes."""
    choice = config.eval_device
    if choice == "auto":
        if hosts.multi:
            choice = "train"
        else:
            choice = "accelerator" if jax.default_backend() == "gpu" else "cpu"
    if choice in OWN_PROCESS and hosts.multi:
        raise ValueError(
            f"eval_device={choice!r} evaluates in one process, and this run has {hosts.count}; "
            "set eval_device='train' or 'auto'"
        )
    _check_eval_processes(config, choice, hosts.multi)
    return choice


def _check_eval_processes(config: ConfigDict, choice: str, multi: bool) -> None:
    """Several evaluation processes need evaluations in processes of their own."""
    if config.eval_processes > 1 and choice not in OWN_PROCESS:
        raise ValueError(
            f"eval_processes={config.eval_processes} evaluates in processes of their own, and "
            f"eval_device={config.eval_device!r} evaluates in the training's (here); set "
            f"eval_processes to 0 or 1, or eval_device to one of {', '.join(OWN_PROCESS)}"
            + (" (a run of several processes evaluates in them)" if multi else "")
        )


def eval_processes(config: ConfigDict, where: str) -> int:
    """How many evaluation processes run side by side for the resolved eval_device `where`
    (`eval_device`'s): config.eval_processes, its 0 resolved to AUTO_EVAL_PROCESSES where they
    run in processes of their own on a GPU machine, else 1 (a CPU-only machine, or evaluations
    in the training's processes)."""
    if config.eval_processes:
        return config.eval_processes
    beside_gpu = where in OWN_PROCESS and jax.default_backend() == "gpu"
    return AUTO_EVAL_PROCESSES if beside_gpu else 1


def render_gpus(setting: str, devices) -> str:
    """env.render.gpus for an env whose lanes live on `devices` (in the order the lanes are split
    over them): "auto" becomes their GPU numbers in this process, as MUJOCO_EGL_DEVICE_ID takes
    them; it stays "auto" where that variable is set, where they are not GPUs, or where they
    are the first GPU alone, MuJoCo's own choice. Numbers stay as given (`validate`)."""
    if setting != "auto":
        return setting
    if os.environ.get("MUJOCO_EGL_DEVICE_ID") or any(d.platform != "gpu" for d in devices):
        return "auto"
    ids = [d.local_hardware_id for d in devices]
    return "auto" if set(ids) == {0} else ",".join(map(str, ids))


def drawing_devices(lane_devices: list, local_devices: list) -> list:
    """The devices env.render.gpus "auto" draws a training env's frames on: the GPUs of this
    process that none of its lanes trains on, up to as many as the lanes' devices, where there
    are any (the first is where evaluations on the accelerator run their policy:
    evaluator.spare_device), else the lanes' own. Drawn beside the updates, the frames' GL work
    slows them: DEAR walker's 5 lanes on one H200 ran at 1,709-1,711 env frames/s drawn on a
    second against 1,355-1,398 (benchmarks/RESULTS.md, "End to end")."""
    idle = [d for d in local_devices if d.platform == "gpu" and d not in lane_devices]
    return idle[: len(lane_devices)] or list(lane_devices)


def make_env(
    config: ConfigDict,
    *,
    envs_per_seed: int,
    split: str,
    seed: int,
    backend: str | None = None,
    mesh: Mesh | None = None,
    hosts: Hosts | None = None,
    physics_threads: int | None = None,
    labels: bool | None = None,
    label_envs: int | None = None,
    video_seed: int | None = None,
    render_devices: list | None = None,
) -> envs.Env:
    """The batched env of the config (`backend` overrides env.backend; seeds split over `mesh`);
    with several processes (`hosts`), of this process's lanes on its devices. physics_threads:
    CPU MuJoCo's threads (default: env.physics_threads, or one per device where that is 0).
    labels: whether the render pool draws the segmentation pass (default: where the method's
    loss reads the agent's mask; the env draws it anyway where it composites backgrounds);
    without it the masks are all 0. label_envs: only the first label_envs envs of each seed draw
    it where no background is composited (envs.Env's). video_seed: the built-in background
    videos' (default: `seed`), the same on every process of the run. render_devices: the
    devices env.render.gpus "auto" draws on (default: `drawing_devices`, GPUs this process's
    lanes leave idle or else theirs)."""
    e = config.env
    hosts = hosts or Hosts(mesh, lanes.num_lanes(config))
    if render_devices is None:
        local = hosts.local
        lane_devices = jax.local_devices()[:1] if local is None else list(local.mesh.devices.flat)
        render_devices = drawing_devices(lane_devices, jax.local_devices())
    render = envs.RenderSettings(
        **e.render.to_dict(),
        labels=config.agent.method in update.MASK_METHODS if labels is None else labels,
    )
    render = dataclasses.replace(render, gpus=render_gpus(render.gpus, render_devices))
    physics_threads = physics_threads or e.physics_threads or hosts.num_devices
    # Each process draws its own lanes' episode starts and distractions from the same videos.
    video_seed = seed if video_seed is None else video_seed
    seed += HOST_SEED_STRIDE * hosts.index
    env = envs.make(
        e.task,
        num_seeds=len(hosts.lanes),
        envs_per_seed=envs_per_seed,
        backend=backend or e.backend,
        distraction=e.distraction,
        distraction_types=e.distraction_types,
        dynamic=e.dynamic,
        background_dir=e.background_dir or None,
        split=split,
        mask=e.mask,
        mask_drop_prob=e.mask_drop_prob,
        render=render,
        seed=seed,
        video_seed=video_seed,
        action_repeat=e.action_repeat,
        episode_frames=e.episode_frames or None,
        sharding=hosts.local,
        physics_threads=physics_threads,
        label_envs=label_envs,
    )
    return env


def make_eval_env(
    config: ConfigDict,
    *,
    mesh: Mesh | None = None,
    hosts: Hosts | None = None,
    stream: int = 0,
    device: jax.Device | None = None,
) -> envs.Env:
    """The evaluation episodes' env: num_eval_episodes envs per seed of the validation split,
    its own seed (evaluation process `stream`'s own, of `eval_processes`; the built-in videos
    every stream's, so that each evaluation shows the same set), env.eval_backend's
    physics; CPU physics on env.eval_physics_threads threads (0: as many as this process may
    use cores, up to 8). device: where the evaluation's policy runs, if not on the lanes'
    devices (its frames are then drawn there: env.render.gpus "auto")."""
    usable = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count())
    threads = config.env.eval_physics_threads or min(8, len(usable))
    return make_env(
        config,
        envs_per_seed=config.num_eval_episodes,
        split="val",
        seed=config.seed + 1 + stream * EVAL_STREAM_STRIDE,
        video_seed=config.seed + 1,
        # The policy reads no mask: only the video's env (env 0 of each seed) shows one.
        labels=config.save_video,
        label_envs=1,
        backend="cpu" if config.env.eval_backend == "cpu" else None,
        mesh=mesh,
        hosts=hosts,
        physics_threads=threads,
        render_devices=None if device is None else [device],
    )


def replay_store(config: ConfigDict, spec: envs.EnvSpec, workdir: pathlib.Path, hosts: Hosts):
    """The chunk store of the replay on disk (None when replay.disk is off), its size checked."""
    if not config.replay.disk:
        return None
    num_envs = config.envs_per_seed
    rows = math.ceil(config.replay.capacity / num_envs)
    chunk_rows = replay_disk.chunk_rows_for(config.replay.chunk_entries, num_envs, rows)
    # Rows are batched env steps: each adds E x action_repeat frames per seed, and every episode
    # adds one more row, its first timestep.
    per_frame = (spec.episode_steps + 1) / spec.episode_steps / (num_envs * spec.action_repeat)
    total_rows = math.ceil(config.total_frames * per_frame) + 1
    ckpt_every = config.checkpoint_every_frames
    between = math.ceil(ckpt_every * per_frame) + 1 if ckpt_every else total_rows
    need = replay_disk.disk_bound(
        num_seeds=len(hosts.lanes),
        rows=rows,
        chunk_rows=chunk_rows,
        num_envs=num_envs,
        entry_bytes=replay.entry_bytes(spec.frame_shape, spec.action_dim),
        rows_between_checkpoints=between,
        keep_checkpoints=config.keep_checkpoints,
        total_rows=total_rows,
    )
    directory = workdir / "replay"
    more, free = replay_disk.check_disk(directory, need)
    gib = 2**30
    log.info(
        "replay on disk in %s: up to %.2f GiB (uncompressed bound, %.2f GiB more than now; "
        "%.2f GiB free); replay.disk=False turns it off",
        directory,
        need / gib,
        more / gib,
        free / gib,
    )
    return replay_disk.ChunkStore(
        directory, len(hosts.lanes), rows, chunk_rows, first_seed=hosts.lanes[0], read=hosts.read
    )
