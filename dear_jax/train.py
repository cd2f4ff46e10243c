"""The training loop: S lanes (seeds, or settings x seeds: `dear_jax/lanes.py`) as a vmapped
axis, E environments per lane, one process.

One iteration (DESIGN.md): act for every seed and env on the accelerator -> hand the actions to
the env (CPU physics steps on its thread; MJX physics is dispatched) -> dispatch E /
update_every_steps updates per seed while the env thread renders the new observations on CPU
workers -> add the new timestep to each seed's replay. The main thread waits on the accelerator
only once per episode or log interval (a few scalars for the logs) and, while an evaluation runs
in the background, for each update before dispatching the next (`_Run._step`); the env thread
waits for the actions (CPU physics) or the physics state (MJX) it needs. Evaluations in the
background queue up to MAX_PENDING_EVALS deep (`_Run._evaluate_if_due`).

`train(config, workdir)` runs (or resumes) a whole experiment and returns its summary. A resume
continues exactly where the checkpoint left off (`_Run` says what a checkpoint holds; the replay
comes back from its chunk files, `dear_jax/replay_disk.py`), and is refused if a config field
that changes learning differs (all but RESUMABLE_CHANGES). One run per workdir (`run.lock`);
SIGTERM / SIGINT checkpoint and stop (`dear_jax/signals.py`).

Several devices (`config.devices`): the seeds axis of every array the loop carries (agent,
replay, env states and timesteps, returns) is split over a 1-D mesh of N local devices, axis
"seeds", each device holding S / N seeds; act, learn and add run per device (`jax.shard_map`,
no collectives: seeds are independent), physics and the env's device half stay where their seeds
live, and one render pool on the host feeds them all. Each seed gets the key it gets on one
device, so its run is the same bit for bit. `devices=1` keeps arrays uncommitted on the default
device, with no mesh.

Several processes (`jax.distributed`, README "Several hosts"): the mesh spans every process's
`config.devices` devices and the loop's arrays are global; each process steps, renders, logs and
stores its own block of lanes (`Hosts`), and every decision that issues a program is made from
values all processes agree on (`Hosts.agree`), so all run the same programs in the same order.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import logging
import math
import os
import pathlib
import signal
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from ml_collections import ConfigDict

import envs
from dear_jax import augment, lanes, losses, networks, replay, replay_disk, update
from dear_jax.checkpoint import Checkpointer, IncompatibleCheckpointError
from dear_jax.evaluator import EvalAborted, EvalProcess, LocalEvaluator
from dear_jax.lock import WorkdirLock
from dear_jax.logger import RunLogger, format_table, read_csv, write_text_atomic
from dear_jax.provenance import provenance
from dear_jax.signals import Stopped, StopRequest
from envs import distractions

log = logging.getLogger("dear_jax")

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
    "env.eval_backend",
    "env.physics_threads",
    "env.eval_physics_threads",
    "eval_in_background",
    "eval_device",
    "agent.seed_axis",
    "agent.shift_impl",
    "agent.filter_gradient",
    "agent.conv_stack",
    "replay.disk",
    "devices",
)


def _flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def fingerprint(config: ConfigDict) -> dict:
    """Every config field that changes what a run learns (all but RESUMABLE_CHANGES), dotted."""
    return {k: v for k, v in _flatten(config.to_dict()).items() if k not in RESUMABLE_CHANGES}


# Offset of process p's env seeds (and episode-start keys): p * HOST_SEED_STRIDE.
HOST_SEED_STRIDE = 1_000_033

EVAL_DEVICES = ("auto", "cpu", "accelerator", "train")
OWN_PROCESS = ("cpu", "accelerator")  # eval_device values that evaluate in a child process
# Background evaluations started and not yet logged before the loop waits for the oldest: two
# absorb one that outlasts the training between two (on an H100 an evaluation of the DrQ-v2
# learning check takes about as long as that training, benchmarks/RESULTS.md), and a stop still
# waits for at most two evaluations before its checkpoint.
MAX_PENDING_EVALS = 2


def _get(config: ConfigDict, dotted: str):
    for part in dotted.split("."):
        config = config[part]
    return config


def num_devices(devices, seeds: int, available: int) -> int:
    """`config.devices` ("all" or an int) as a device count, refused unless it fits the host's
    `available` devices and splits the `seeds` evenly (a sweep's lanes: seeds x settings)."""
    if devices == "all":
        n = available
    elif isinstance(devices, int) and not isinstance(devices, bool) and devices >= 1:
        n = devices
    else:
        raise ValueError(f"devices must be 'all' or an int >= 1, got {devices!r}")
    if n > available:
        counts = "1" if available == 1 else f"1 to {available}"
        raise ValueError(
            f"devices={devices} but {available} {jax.default_backend()} device(s) exist here; "
            f"valid: {counts}, or 'all'"
        )
    if seeds % n:
        valid = [d for d in range(1, available + 1) if seeds % d == 0]
        raise ValueError(
            f"seeds={seeds} cannot be split evenly over devices={devices} ({n} devices); valid "
            f"devices for {seeds} seeds: {', '.join(map(str, valid))}; or make seeds a multiple "
            f"of {n}"
        )
    return n


def seed_mesh(config: ConfigDict) -> Mesh | None:
    """The 1-D mesh ("seeds") of the first `config.devices` local devices; None for one device.
    With several processes, of the first `config.devices` devices of every process, in process
    order: process p holds the p-th block of lanes."""
    hosts = jax.process_count()
    per_host = lanes_per_host(lanes.num_lanes(config), hosts)
    n = num_devices(config.devices, per_host, jax.local_device_count())
    if hosts == 1:
        return None if n == 1 else Mesh(np.array(jax.local_devices()[:n]), ("seeds",))
    devices = [[d for d in jax.devices() if d.process_index == p][:n] for p in range(hosts)]
    return Mesh(np.array(sum(devices, [])), ("seeds",))


def lanes_per_host(num_lanes: int, hosts: int) -> int:
    """Lanes per process, refused unless the processes split them evenly."""
    if num_lanes % hosts:
        valid = [h for h in range(1, num_lanes + 1) if num_lanes % h == 0]
        raise ValueError(
            f"{num_lanes} lanes (seeds x sweep settings) cannot be split evenly over {hosts} "
            f"processes; valid process counts: {', '.join(map(str, valid))}; or make the lanes "
            f"a multiple of {hosts}"
        )
    return num_lanes // hosts


def seed_sharding(mesh: Mesh | None) -> NamedSharding | None:
    """Arrays with a leading seeds axis split over `mesh` (None: no mesh, the default device)."""
    return None if mesh is None else NamedSharding(mesh, P("seeds"))


class Hosts:
    """This process's share of a run's arrays. One process: every array is whole here and the
    methods do nothing. Several (`jax.distributed`): the loop's arrays are global (split over
    `mesh`, every process's devices), while this process's envs, logs and replay files hold its
    block of lanes (`lanes`) on its own devices (`local`, the env's sharding); the methods move
    between the two without copies, and `agree` is the one place processes exchange values."""

    def __init__(self, mesh: Mesh | None, num_lanes: int):
        self.count, self.index = jax.process_count(), jax.process_index()
        self.mesh = mesh
        per_host = num_lanes // self.count
        self.lanes = range(self.index * per_host, (self.index + 1) * per_host)
        self.local = seed_sharding(mesh)
        if self.count > 1:
            mine = [d for d in mesh.devices if d.process_index == self.index]
            self.local = NamedSharding(Mesh(np.array(mine), ("seeds",)), P("seeds"))

    @property
    def multi(self) -> bool:
        return self.count > 1

    @property
    def num_devices(self) -> int:
        """The devices this process trains on."""
        return 1 if self.local is None else len(self.local.device_set)

    def _shards(self, x) -> list:
        """x's shards on this process's devices, in mesh order."""
        by_device = {s.device: s.data for s in x.addressable_shards}
        return [by_device[d] for d in self.local.mesh.devices]

    def to_global(self, tree):
        """This process's block [S / P, ...] (on `local`) -> the run's array [S, ...]; 0-d
        leaves, which must be the same on every process -> replicated."""
        if not self.multi:
            return tree

        def one(x):
            if x.ndim == 0:
                return self.place(x, NamedSharding(self.mesh, P()))
            if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
                data = one(jax.random.key_data(x))
                return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
            shape = (x.shape[0] * self.count, *x.shape[1:])
            return jax.make_array_from_single_device_arrays(
                shape, seed_sharding(self.mesh), self._shards(x)
            )

        return jax.tree.map(one, tree)

    def to_local(self, tree):
        """The run's arrays [S, ...] -> this process's block [S / P, ...] on `local`; replicated
        0-d leaves -> uncommitted arrays here."""
        if not self.multi:
            return tree

        def one(x):
            if x.ndim == 0:
                return _uncommitted(x.addressable_data(0))
            if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
                data = one(jax.random.key_data(x))
                return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
            shape = (x.shape[0] // self.count, *x.shape[1:])
            return jax.make_array_from_single_device_arrays(shape, self.local, self._shards(x))

        return jax.tree.map(one, tree)

    def read(self, x) -> np.ndarray:
        """This process's block of a [S, ...] array, on the host."""
        if not self.multi:
            return np.asarray(x)
        return np.concatenate([np.asarray(a) for a in self._shards(x)])

    def place(self, x, sharding):
        """A value every process holds whole and alike, placed over the run's devices."""
        if not self.multi:
            return jax.device_put(x, sharding)
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            data = self.place(jax.random.key_data(x), sharding)
            return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    def place_local(self, x: np.ndarray):
        """This process's block [S / P, ...] of host values -> the run's array [S, ...]."""
        shape = (x.shape[0] * self.count, *x.shape[1:])
        return jax.make_array_from_process_local_data(seed_sharding(self.mesh), x, shape)

    def agree(self, values) -> np.ndarray:
        """[processes, k]: every process's `values` (k numbers), the same on every process."""
        values = np.asarray(values, np.int64)
        if not self.multi:
            return values[None]
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(values)).reshape(self.count, -1)


def validate(config: ConfigDict) -> None:
    """Fail early, naming the field and the valid choices."""
    if config.env.task not in envs.names():
        raise ValueError(f"unknown env.task {config.env.task!r}; valid: {', '.join(envs.names())}")
    choices = {
        "agent.method": update.METHODS,
        "agent.encoder": ("pool", "plain"),
        "agent.ortho_form": losses.ORTHOGONALITY_FORMS,
        "agent.seed_axis": update.SEED_AXES,
        "agent.shift_impl": augment.SHIFT_IMPLS,
        "agent.filter_gradient": networks.FILTER_GRADIENTS,
        "agent.conv_stack": networks.STACKS,
        "env.backend": ("auto", "mjx", "cpu"),
        "env.eval_backend": ("cpu", "train"),
        "eval_device": EVAL_DEVICES,
        "env.distraction": ("none", "easy", "medium", "hard"),
        "env.mask": ("true", "noisy", "approximate"),
    }
    for key, valid in choices.items():
        if _get(config, key) not in valid:
            raise ValueError(f"unknown {key} {_get(config, key)!r}; valid: {', '.join(valid)}")
    try:
        distractions.parse_types(config.env.distraction_types)
    except ValueError as e:
        raise ValueError(f"env.distraction_types: {e}") from None
    positive = (
        "seeds",
        "envs_per_seed",
        "total_frames",
        "eval_every_frames",
        "num_eval_episodes",
        "agent.batch_size",
        "agent.nstep",
        "agent.update_every_steps",
        "replay.capacity",
    )
    for key in positive:
        if _get(config, key) < 1:
            raise ValueError(f"{key} must be >= 1, got {_get(config, key)}")
    for key, auto in [
        ("env.physics_threads", "one per device"),
        ("env.eval_physics_threads", "one per core, up to 8"),
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
    if a.batch_size > r.capacity:
        raise ValueError(
            f"agent.batch_size={a.batch_size} is larger than the replay "
            f"(replay.capacity={r.capacity}); lower the batch or raise the capacity"
        )
    lanes.sweep_values(config)  # unknown or ineffective sweep keys
    per_host = lanes_per_host(lanes.num_lanes(config), jax.process_count())
    num_devices(config.devices, per_host, jax.local_device_count())
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
        compute_dtype=a.compute_dtype,
        shift_impl=a.shift_impl,
        filter_gradient=a.filter_gradient,
        conv_stack=a.conv_stack,
    )


def hparams(config: ConfigDict) -> update.HParams:
    """The update's per-lane numbers: [lanes] arrays, the config's values and the sweep's."""
    a = config.agent
    runs = lanes.lanes(config)
    names = [f.name for f in dataclasses.fields(update.HParams)]
    return update.HParams(
        **{n: jnp.array([dict(r.settings).get(n, a[n]) for r in runs], jnp.float32) for n in names}
    )


def eval_device(config: ConfigDict, hosts: Hosts) -> str:
    """Where the evaluations run (config.eval_device, "auto" resolved): a process of their own
    on the host's CPU ("cpu") or on the training's accelerator ("accelerator";
    dear_jax/evaluator.py), or "train", this process.

    "auto" is "accelerator" for a run of one process on a GPU: on an H100 its evaluations slowed
    training less than "cpu" did (benchmarks/RESULTS.md, "Where an evaluation's cost goes");
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
    return choice


def make_env(
    config: ConfigDict,
    *,
    envs_per_seed: int,
    split: str,
    seed: int,
    backend: str | None = None,
    mesh: Mesh | None = None,
    hosts: Hosts | None = None,
    physics_threads: int = 1,
) -> envs.Env:
    """The batched env of the config (`backend` overrides env.backend; seeds split over `mesh`);
    with several processes (`hosts`), of this process's lanes on its devices. physics_threads:
    CPU MuJoCo's threads."""
    e = config.env
    hosts = hosts or Hosts(mesh, lanes.num_lanes(config))
    # Each process draws its own lanes' episode starts and distractions.
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
        render=envs.RenderSettings(**e.render.to_dict()),
        seed=seed,
        action_repeat=e.action_repeat,
        episode_frames=e.episode_frames or None,
        sharding=hosts.local,
        physics_threads=physics_threads,
    )
    return env


def make_eval_env(
    config: ConfigDict, *, mesh: Mesh | None = None, hosts: Hosts | None = None
) -> envs.Env:
    """The evaluation episodes' env: num_eval_episodes envs per seed of the validation split,
    its own seed, env.eval_backend's physics; CPU physics on env.eval_physics_threads threads
    (0: as many as this process may use cores, up to 8)."""
    usable = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count())
    threads = config.env.eval_physics_threads or min(8, len(usable))
    return make_env(
        config,
        envs_per_seed=config.num_eval_episodes,
        split="val",
        seed=config.seed + 1,
        backend="cpu" if config.env.eval_backend == "cpu" else None,
        mesh=mesh,
        hosts=hosts,
        physics_threads=threads,
    )


@dataclasses.dataclass(frozen=True)
class Programs:
    """The jitted functions of the loop, each over all seeds at once."""

    act: callable  # (agent, obs [S,E,...], key, stepping [S,E]) -> (actions [S,E,A], agent)
    learn: callable  # (agent, replay, key) -> (agent, metrics [S]): one update per seed
    add: callable  # (replay, ts, action) -> replay
    # (params, obs) -> (actions, {cos_agent_env, abs_cos_agent_env: [S]}, predicted mask of env 0
    # [S,H,W])
    evaluate_step: callable
    # The same in float32, for the evaluation process on the host's CPU (eval_device="cpu",
    # dear_jax/evaluator.py): XLA:CPU runs bfloat16 convolutions at half float32's speed.
    evaluate_step_host: callable
    accumulate: callable  # (returns [S,E], ts) -> returns
    add_metrics: callable  # (metrics, metrics) -> elementwise sum


_PROGRAMS: dict = {}


def cached_programs(
    acfg: update.AgentConfig, config: ConfigDict, mesh: Mesh | None = None
) -> Programs:
    """build_programs, reused by later runs of this process with the same agent and seeds (tests,
    resumes in one process): their jitted functions are then compiled once per mesh."""
    settings = {k: config[k].to_dict() for k in ("agent", "sweep")}
    experiment = (acfg, config.seeds, json.dumps(settings, sort_keys=True))
    if (experiment, mesh) not in _PROGRAMS:
        hp = hparams(config)
        for key in [k for k in _PROGRAMS if k[0] != experiment]:
            del _PROGRAMS[key]  # a process runs one experiment at a time
        _PROGRAMS[experiment, mesh] = build_programs(acfg, hp, config, mesh)
    return _PROGRAMS[experiment, mesh]


def build_programs(
    acfg: update.AgentConfig, hp: update.HParams, config: ConfigDict, mesh: Mesh | None = None
) -> Programs:
    """The loop's programs; with a `mesh`, act, learn and add run each device's block of seeds
    on that device. Per-seed keys are split before the split over devices, so a seed draws the
    same numbers on any number of devices."""
    a = config.agent
    num_seeds = lanes.num_lanes(config)
    nets = update.make_networks(acfg)

    def per_device(fn):
        """`fn` of a block of seeds ([S / N, ...] arguments), run where the block lives."""
        if mesh is None:
            return fn
        # check_vma=False: the bodies hold no collectives (each device runs its own seeds), so
        # there is nothing for shard_map's varying-axes types to check, and every output varies
        # over "seeds" by construction. With the check on, each pallas_call (wideconv, wgrad)
        # would have to state its outputs' varying axes in its out_shape, a jax-version-specific
        # annotation kernels meant for one device do not carry; without it, tracing fails.
        return jax.shard_map(
            fn, mesh=mesh, in_specs=P("seeds"), out_specs=P("seeds"), check_vma=False
        )

    # Acting, updating and evaluating run their seeds as agent.seed_axis says (sampling is always
    # vmapped: integer work, gathers and element-wise sums, the same for any number of seeds).
    # With "loop", a seed's computation is the same however many seeds share its device, so a
    # split run is the same bit for bit; a vmapped convolution of S seeds is one grouped
    # convolution whose rounding depends on S.
    def over_seeds(fn):
        return per_device(update.over_seeds(fn, a.seed_axis))

    def act(agent, obs, key, stepping):
        keys = jax.random.split(key, num_seeds)

        def per_seed(agent, obs, key, hp, stepping):
            return update.act(acfg, agent, obs, key, hp, explore=True, stepping=stepping)

        return over_seeds(per_seed)(agent, obs, keys, hp, stepping)

    def sample_one(buffer, key):
        return replay.sample(
            buffer,
            key,
            a.batch_size,
            nstep=a.nstep,
            gamma=a.discount,
            frame_stack=acfg.frame_stack,
            same_episode=acfg.method == "ted",
        )

    def update_one(agent, batch, key, hp_seed):
        return update.update(agent, batch, key, hp_seed, cfg=acfg)

    # One update per seed per call; the loop calls it E / update_every_steps times (dispatch is
    # asynchronous). A lax.scan over the updates made tests/test_run.py's tiny runs ~3x slower
    # on CPU (its fixture: 298 s with the scan, 97 s without; pytest --durations).
    # Batches are drawn for all seeds at once (vmapped gathers from the [S, T, E, ...] replay);
    # only the updates follow agent.seed_axis. Looping the sampling too, which slices each
    # seed's replay out of the buffer first, made DEAR's learn program on an H100 take 395
    # instead of 295 ms per 5 x 16 iteration (benchmarks/RESULTS.md, "The training loop").
    def learn_block(agent, buffer, keys, hp):
        k_sample, k_update = jnp.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0)
        batches = jax.vmap(sample_one)(buffer, k_sample)
        return update.over_seeds(update_one, a.seed_axis)(agent, batches, k_update, hp)

    def learn(agent, buffer, key):
        keys = jax.random.split(key, num_seeds)
        return per_device(learn_block)(agent, buffer, keys, hp)

    def add(buffer, ts, action):
        return per_device(jax.vmap(replay.add))(
            buffer, ts.frame, ts.mask, action, ts.reward, ts.discount, ts.first
        )

    def evaluate_step(nets):
        def one(params, obs):
            z = nets.encoder.apply({"params": params["encoder"]}, obs)
            action = nets.actor.apply({"params": params["actor"]}, z)
            z_env, z_agent = losses.split_latent(z)
            cos = losses.latent_cosines(z_agent, z_env)
            if nets.mask_decoder is None:
                pred = jnp.zeros(obs.shape[1:3])
            else:  # newest frame's channel of env 0
                logits = nets.mask_decoder.apply({"params": params["mask_decoder"]}, z_agent[:1])
                pred = jax.nn.sigmoid(logits[0, ..., -1])
            return action, cos, pred

        return one

    nets_f32 = update.make_networks(dataclasses.replace(acfg, compute_dtype="float32"))

    def accumulate(returns, ts):
        return jnp.where(ts.first, 0.0, returns) + ts.reward

    return Programs(
        act=jax.jit(act, donate_argnums=0),
        learn=jax.jit(learn, donate_argnums=0),
        add=jax.jit(add, donate_argnums=0),
        evaluate_step=jax.jit(over_seeds(evaluate_step(nets))),
        evaluate_step_host=jax.jit(update.over_seeds(evaluate_step(nets_f32), a.seed_axis)),
        accumulate=jax.jit(accumulate),
        add_metrics=jax.jit(lambda a, b: jax.tree.map(jnp.add, a, b)),
    )


def _pbar(config, total, initial):
    """The progress bar, on a terminal only (detached runs log a line per log interval instead)."""
    if not config.progress or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        unit="frame",
        desc="frames per seed",
        smoothing=0.05,
        dynamic_ncols=True,
    )


def _replay_store(config: ConfigDict, spec: envs.EnvSpec, workdir: pathlib.Path, hosts: Hosts):
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


def train(config: ConfigDict, workdir: str | pathlib.Path) -> dict:
    """Run (or resume) the experiment described by `config` in `workdir`; returns the summary.

    SIGTERM or SIGINT: the run checkpoints at the end of its step, writes its summary so far
    (`"stopped"`: the signal's name) and raises signals.Stopped.
    """
    validate(config)
    mesh = seed_mesh(config)
    hosts = Hosts(mesh, lanes.num_lanes(config))
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        stack.enter_context(WorkdirLock(workdir, hosts.index))
        stop = stack.enter_context(StopRequest())

        def checkpointer() -> Checkpointer:
            ckpt = Checkpointer(
                workdir / "checkpoints",
                fingerprint=fingerprint(config),
                keep=config.keep_checkpoints,
            )
            stack.callback(ckpt.close)
            return ckpt

        ckpt = None
        if (workdir / "checkpoints").is_dir():  # a changed config is refused before anything
            ckpt = checkpointer()
            if ckpt.latest_step() is not None:
                step, saved, extra = ckpt.read_meta()
                ckpt.check_fingerprint(saved, step)
                if extra.get("processes", 1) != hosts.count:
                    raise IncompatibleCheckpointError(
                        f"checkpoint {step} in {ckpt.directory} was written by "
                        f"{extra.get('processes', 1)} process(es), and this run has "
                        f"{hosts.count}; resume with as many processes (each holds the host state "
                        "of its lanes' envs), or start in a new --workdir"
                    )
        env = stack.enter_context(
            make_env(
                config,
                envs_per_seed=config.envs_per_seed,
                split="train",
                seed=config.seed,
                mesh=mesh,
                hosts=hosts,
                physics_threads=config.env.physics_threads or hosts.num_devices,
            )
        )
        spec = env.spec
        if config.agent.nstep > spec.episode_steps:
            raise ValueError(
                f"agent.nstep={config.agent.nstep} is longer than an episode of {spec.name} "
                f"({spec.episode_steps} agent steps); lower agent.nstep"
            )
        runs = lanes.lanes(config)
        mine = [runs[i] for i in hosts.lanes]  # the lanes whose envs, logs and files are here
        lanes_per_device = len(runs) // (1 if mesh is None else mesh.size)
        replay.check_fits(
            lanes_per_device, config.replay.capacity, spec.frame_shape, spec.action_dim
        )
        ckpt = ckpt or checkpointer()  # a new run's folder: only once the config is known to work
        store = _replay_store(config, spec, workdir, hosts)
        if store is not None:
            stack.callback(store.close)
        where = eval_device(config, hosts)
        log.info("evaluations: eval_device=%r (config: %r)", where, config.eval_device)
        if where in OWN_PROCESS:  # starts now, builds while this compiles
            evaluator = EvalProcess(config)
        else:
            eval_env = make_eval_env(config, mesh=mesh, hosts=hosts)
            acfg = agent_config(config, spec.action_dim)
            evaluator = LocalEvaluator(
                eval_env, cached_programs(acfg, config, mesh).evaluate_step, hosts
            )
        stack.callback(evaluator.close)
        if mesh is not None:
            log.info(
                "%d lanes split over %d devices (%d each) of %d process(es): %s; here lanes "
                "%d to %d",
                len(runs),
                mesh.size,
                lanes_per_device,
                hosts.count,
                ", ".join(str(d) for d in mesh.devices),
                hosts.lanes[0],
                hosts.lanes[-1],
            )
        run = _Run(config, spec, ckpt, store, env, evaluator, mesh, hosts)
        if hosts.index == 0:
            (workdir / "config.json").write_text(config.to_json(indent=1))
        names = [lane.name for lane in mine]
        # An evaluation due at the checkpoint's frame runs again (and logs its row again).
        redo = ("eval",) if run.resumed_from is not None and run.eval_due() else ()
        logger = RunLogger(
            workdir, len(mine), names=names, resume_frame=run.resumed_from, redo=redo
        )
        if len(runs) > 1 or runs[0].settings:  # each lane's own settings beside its logs
            for i, lane in enumerate(mine):
                text = lanes.lane_config(config, lane).to_json(indent=1)
                (logger.seed_dir(i) / "config.json").write_text(text)
        stack.callback(logger.close)
        stop = run.agreed_stop(stop)
        run.loop(logger, workdir, stop)
    if hosts.multi:  # every process's logs are written before process 0 sums them up
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("dear_jax: logs written")
    devices = 1 if mesh is None else mesh.size
    # A stopped run's summary is of what it has done so far (the report reads it); the resumed
    # run rewrites it.
    summary = {}
    if not hosts.index:
        try:
            summary = write_summary(
                workdir,
                config,
                spec,
                run.counters,
                devices=devices,
                stopped=stop.name if stop else None,
                evaluated_on=where,
            )
        except Exception as e:  # a stopped run still exits as stopped (and resumable)
            if not stop:
                raise
            log.warning("the stopped run's summary was not written: %s", e)
    if stop:
        raise Stopped(
            f"stopped by {stop.name} at frame {run.counters['frame']:,} per seed; checkpoint "
            f"saved in {workdir / 'checkpoints'}; rerun the same command to resume",
            stop.signum,
        )
    return summary


def _is_host(x) -> bool:
    return isinstance(x, (np.ndarray, np.generic))


def _to_host(x) -> np.ndarray:
    if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
        x = jax.random.key_data(x)
    return np.asarray(x)


def _like(template, value):
    """`value`, a host copy of a leaf like `template` (`_to_host`), as `template` is."""
    if _is_host(template):
        return value
    if jnp.issubdtype(template.dtype, jax.dtypes.prng_key):
        return jax.random.wrap_key_data(jnp.asarray(value), impl=jax.random.key_impl(template))
    return jnp.asarray(value)


def _uncommitted(x):
    """`x` as a fresh run has it: a device array not committed to a device. jit compiles
    separately for committed arguments (orbax restores those), so a resumed run would otherwise
    compile every program of the loop twice."""
    if not isinstance(x, jax.Array):
        return x
    if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
        data = jnp.asarray(np.asarray(jax.random.key_data(x)))
        return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
    return jnp.asarray(np.asarray(x))


_init_seeds = jax.jit(update.init_seeds, static_argnums=0)


class _Trace:
    """config.profile: a jax.profiler trace of a few loop iterations, to workdir/profile (with
    several processes, workdir/profile/process_<p>)."""

    def __init__(self, settings: ConfigDict, workdir: pathlib.Path, frame: int):
        self.at, self.left = settings.at_frame, settings.iterations
        self.directory = workdir / "profile"
        if jax.process_count() > 1:
            self.directory = self.directory / f"process_{jax.process_index()}"
        self.on = False
        if self.at < frame:  # off, or a resumed run past the frame: traced before, if ever
            self.left = 0

    def tick(self, frame: int, sync) -> None:
        """Called before each iteration; `sync` waits for the device work dispatched so far."""
        if self.on:
            self.left -= 1
            if not self.left:
                self.stop(sync)
        elif self.left > 0 and self.at <= frame:
            sync()  # the trace starts with an empty queue, so it holds whole iterations
            try:
                jax.profiler.start_trace(str(self.directory))
            except RuntimeError as e:  # e.g. another trace already running in this process
                log.warning("profile not taken: %s", e)
                self.left = 0
                return
            self.on = True

    def stop(self, sync=None) -> None:
        """End the trace; `sync` first waits for the work it covers (None: a run failing)."""
        if self.on:
            self.on, self.left = False, 0
            if sync is not None:
                sync()
            jax.profiler.stop_trace()
            log.info("profile of the loop written to %s (tensorboard --logdir)", self.directory)


class _AgreedStop:
    """A StopRequest as several processes read it: set by `_Run._step` once any process got
    a signal (`request`: this process's own), on every process at the same step."""

    def __init__(self, request: StopRequest):
        self.request, self.signum = request, None

    def __bool__(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""


class _Run:
    """The host side of one training run: agent, replay, envs mid-episode, keys, counters.

    Everything the loop carries from one step to the next is here, and a checkpoint holds all
    of it (`_tree`: arrays; `_extra`: host values), so a resumed run continues exactly as the
    uninterrupted one: same updates, same parameters bit for bit, same log rows.
    """

    def __init__(
        self,
        config,
        spec,
        ckpt: Checkpointer,
        store,
        env: envs.Env,
        evaluator: LocalEvaluator | EvalProcess,
        mesh: Mesh | None = None,
        hosts: Hosts | None = None,
    ):
        self.config, self.spec, self.ckpt, self.store = config, spec, ckpt, store
        self.env, self.evaluator, self.mesh = env, evaluator, mesh
        self.lanes = lanes.lanes(config)
        self.hosts = hosts or Hosts(mesh, len(self.lanes))
        self.mine = [self.lanes[i] for i in self.hosts.lanes]
        num_seeds, num_envs = len(self.lanes), config.envs_per_seed
        self.acfg = agent_config(config, spec.action_dim)
        self.programs = cached_programs(self.acfg, config, mesh)
        root = jax.random.key(config.seed)
        # Lanes of one seed (a sweep's settings) start from the same parameters.
        lane_seeds = jnp.array([lane.seed for lane in self.lanes])
        seed_keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(lane_seeds)
        self.agent = self._split(_init_seeds(self.acfg, seed_keys))
        # Made where it lives: the replay of all lanes may not fit on one device.
        self.buffer = jax.jit(
            functools.partial(
                replay.init,
                config.replay.capacity,
                num_envs,
                spec.frame_shape,
                spec.action_dim,
                leading=(num_seeds,),
            ),
            **({} if mesh is None else {"out_shardings": seed_sharding(mesh)}),
        )()
        self.key = self._everywhere(jax.random.fold_in(root, 1_000_003))
        # Evaluations draw from their own stream (one key per frame), so how often a run
        # evaluates never changes its training.
        self.eval_root = jax.random.fold_in(root, 2_000_003)
        self.counters = {
            "frame": 0,
            "iteration": 0,
            "episode": 0,
            "updates": 0,
            "rows": 0,  # rows added to the replay (its row r lives in ring row r % T)
            "wall_s": 0.0,
        }
        self.lv = {  # loop variables carried between steps
            "steps_owed": 0.0,  # agent steps per seed not yet matched by updates
            "seed_frames": config.replay.seed_frames,  # the frame updates start at
            "env_steps": 0,  # agent steps taken, summed over all seeds' envs
            "episodes_ended": 0,  # episodes ended, summed over all seeds' envs
            "metric_count": 0,
            "next_log": config.log_every_frames,
            "last_log_frame": 0,
            "next_eval": 0,  # as DrQ-v2: every curve starts at the untrained policy
            "last_eval_frame": -1,
        }
        self.metric_sum = None  # train metrics summed since the last log row
        self.episode_returns = []  # [2, S] per step: returns summed and count of ended episodes
        self.last_eval_return = None
        # Evaluations started and not yet logged, oldest first (see _evaluate_if_due).
        self._pending_evals: collections.deque[dict] = collections.deque()
        self._closing = False  # the loop has ended: evaluations still in this process abort
        # Several processes must issue their programs in the same order: no second thread.
        self._eval_thread = (
            concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="eval")
            if config.eval_in_background and not self.hosts.multi
            else None
        )
        self._episodes_pending = False  # an episode ended (on any process) since the last row
        self._stop = None  # several processes: the stop request they agree on (agreed_stop)
        self.resumed_from = None
        self.key, k_reset = jax.random.split(self.key)
        self.state, ts = env.reset(self._env_key(k_reset))
        self.ts = self.hosts.to_global(ts)
        self.returns = self._split(jnp.zeros((num_seeds, num_envs)))
        self._no_action = self._split(jnp.zeros((num_seeds, num_envs, spec.action_dim)))
        if ckpt.latest_step() is None:
            if store is not None:
                store.forget_after(0)  # files of an earlier run whose checkpoints were deleted
            self._add(self.ts, self._no_action)
        else:
            self._restore()

    def _split(self, tree):
        """`tree`, whose leaves lead with the seeds axis, split over the devices (if several)."""
        if self.mesh is None:
            return tree
        return jax.tree.map(lambda x: self.hosts.place(x, seed_sharding(self.mesh)), tree)

    def _everywhere(self, tree):
        """`tree` (no seeds axis) on every device of the mesh (if any)."""
        if self.mesh is None:
            return tree
        return jax.tree.map(lambda x: self.hosts.place(x, NamedSharding(self.mesh, P())), tree)

    def _env_key(self, key):
        """A key of the loop (on every device) as this process's envs take it: here, and
        folded with the process index, so processes draw different episode starts."""
        if not self.hosts.multi:
            return key
        return jax.random.fold_in(self.hosts.to_local(key), self.hosts.index)

    def agreed_stop(self, stop: StopRequest):
        """`stop` as the loop reads it: with several processes, true once any process got a
        signal, on every process at the same step (`_step` asks), so all checkpoint together."""
        if self.hosts.multi:
            self._stop = _AgreedStop(stop)
            return self._stop
        return stop

    # -- checkpoints -------------------------------------------------------------------------
    def _saved_on_host(self, x) -> bool:
        """Env state leaves saved with this process's host values: numpy ones and, with several
        processes, the env's key (each process's envs have their own)."""
        return _is_host(x) or (self.hosts.multi and x.ndim == 0)

    def _tree(self) -> dict:
        b = self.buffer
        return {
            "agent": self.agent,
            "key": self.key,
            "env": self.hosts.to_global(
                [x for x in jax.tree.leaves(self.state) if not self._saved_on_host(x)]
            ),
            "ts": self.ts,
            "returns": self.returns,
            "replay": {"episodes_started": b.episodes_started, "pos": b.pos, "size": b.size},
        }

    def _extra(self) -> dict:
        return {
            "counters": dict(self.counters),
            "loop": dict(self.lv),
            "metric_sum": (
                None
                if self.metric_sum is None
                else {k: self.hosts.read(v) for k, v in self.metric_sum.items()}
            ),
            "episode_returns": list(self.episode_returns),
            "env_host": [
                _to_host(x) for x in jax.tree.leaves(self.state) if self._saved_on_host(x)
            ],
            "env_rng": self.env.host_state(),
            "eval_env_rng": self.evaluator.host_state(),
            "replay_on_disk": self.store is not None,
            "processes": self.hosts.count,
        }

    def save(self, wall_s: float) -> None:
        # The loop saves before starting an evaluation due at this frame (see `loop`), so the
        # evaluations in flight or queued here started earlier: their rows and eval-env state
        # belong to this checkpoint.
        self._finish_evaluations(keep=0)
        self.counters["wall_s"] = wall_s
        if self.store is not None:
            self.store.save_partial(self.buffer, self.counters["rows"])
        self.ckpt.save(self.counters["frame"], self._tree(), extra=self._extra())
        if self.store is not None:
            # Row counts of the kept checkpoints of this replay (a checkpoint saved without the
            # replay on disk, before a resume restarted the row count, is not one of them).
            rows = self.counters["rows"]
            metas = (self.ckpt.read_meta(s)[2] for s in self.ckpt.all_steps())
            kept = {
                m["counters"]["rows"]
                for m in metas
                if m.get("replay_on_disk") and m["counters"]["rows"] <= rows
            }
            self.store.prune(rows, kept | {rows})

    def _restore(self) -> None:
        # orbax places arrays as the template's are: on several devices, the current split,
        # whatever the split of the run that saved them.
        step, restored, extra = self.ckpt.restore(self._tree())
        if self.mesh is None:
            restored = jax.tree.map(_uncommitted, restored)
        self.agent, self.key = restored["agent"], restored["key"]
        self.ts, self.returns = restored["ts"], restored["returns"]
        leaves, treedef = jax.tree.flatten(self.state)
        device = iter(self.hosts.to_local(restored["env"]))
        host = iter(extra["env_host"])
        self.state = treedef.unflatten(
            [_like(x, next(host)) if self._saved_on_host(x) else next(device) for x in leaves]
        )
        self.env.set_host_state(extra["env_rng"])
        self.evaluator.set_host_state(extra["eval_env_rng"])
        self.counters = extra["counters"]
        self.lv.update(extra["loop"])
        frame = self.counters["frame"]
        self.lv["last_log_frame"] = frame  # the first rate after a resume counts from here
        if self.lv["next_eval"] > frame:  # none pending: follow this run's eval interval
            self.lv["next_eval"] = (frame // self.config.eval_every_frames + 1) * (
                self.config.eval_every_frames
            )
        if extra["metric_sum"] is not None:
            self.metric_sum = {
                k: self.hosts.place_local(v) if self.hosts.multi else jnp.asarray(v)
                for k, v in extra["metric_sum"].items()
            }
        self.episode_returns = [np.asarray(r) for r in extra["episode_returns"]]
        self._episodes_pending = bool(self.hosts.agree([len(self.episode_returns)]).any())
        self.resumed_from = frame
        rows = self.counters["rows"]
        if self.store is not None and extra["replay_on_disk"]:
            self.store.forget_after(rows)
            t0 = time.perf_counter()
            if self.hosts.multi:  # each process reads its lanes' files into its block
                local = self.store.restore(self.hosts.to_local(self.buffer), rows)
                self.buffer = self.hosts.to_global(local).replace(**restored["replay"])
            else:
                buffer = self.store.restore(self.buffer, rows).replace(**restored["replay"])
                self.buffer = self._split(buffer)
            log.info(
                "resumed from checkpoint %d (frame %d per seed); replay: %d rows per seed read "
                "back from %s in %.0f s",
                step,
                frame,
                min(rows, self.store.rows),
                self.store.directory,
                time.perf_counter() - t0,
            )
        else:
            log.warning(
                "resumed from checkpoint %d (frame %d per seed) without its replay (it was not "
                "kept on disk: replay.disk=False); collecting %d seed frames again before updating",
                step,
                frame,
                self.config.replay.seed_frames,
            )
            self.lv["seed_frames"] = frame + self.config.replay.seed_frames
            self.counters["rows"] = 0
            if self.store is not None:
                self.store.forget_after(0)
            # The env is mid-episode; the empty replay starts an episode at its current timestep.
            self._add(self.ts.replace(first=jnp.ones_like(self.ts.first)), self._no_action)

    # -- one step ----------------------------------------------------------------------------
    def _add(self, ts, action) -> None:
        self.buffer = self.programs.add(self.buffer, ts, action)
        self.counters["rows"] += 1
        if self.store is not None:
            self.store.added(self.buffer, self.counters["rows"])

    def _step(self, pbar) -> None:
        config, programs, counters, lv = self.config, self.programs, self.counters, self.lv
        hosts = self.hosts
        self.key, k_act, k_learn = jax.random.split(self.key, 3)
        # An env whose episode ended restarts this step: it shows a first frame, adds no
        # transition and owes no update. DMC envs all end together; kitchen envs end on success.
        stepping = ~np.asarray(self.state.last)  # [S, E]; several processes: [S / P, E], here
        # The step's decisions use sums over every process's envs (and any process's stop
        # request), so that all of them dispatch the same programs.
        request = getattr(self._stop, "request", None)
        steps, signum = hosts.agree([stepping.sum(), (request and request.signum) or 0]).T
        steps = int(steps.sum())
        if signum.any():
            self._stop.signum = int(signum.max())
        steps_per_seed = steps / len(self.lanes)
        if hosts.multi:
            stepping = hosts.place_local(stepping)
        action, self.agent = programs.act(self.agent, self.ts.obs, k_act, stepping)
        future = self.env.step_async(self.state, hosts.to_local(action))
        # Updates are dispatched while the env thread renders the next observations.
        if counters["frame"] >= lv["seed_frames"] and steps_per_seed:
            lv["steps_owed"] += steps_per_seed / config.agent.update_every_steps
            n = int(lv["steps_owed"])
            lv["steps_owed"] -= n
            if n and not counters["updates"]:  # once: the replay must hold a batch
                replay.check_can_sample(
                    replay.num_transitions(hosts.to_local(self.buffer), self.acfg.frame_stack),
                    config.agent.batch_size,
                )
            # While an evaluation runs in the background on the training's devices, its steps'
            # programs queue behind the updates dispatched before them: each update is
            # dispatched only once the one before it has finished, so they wait for one update,
            # not for all. (An evaluation in a process of its own queues nothing here.)
            short_queue = (
                bool(self._pending_evals)
                and self._eval_thread is not None
                and isinstance(self.evaluator, LocalEvaluator)
            )
            for k in jax.random.split(k_learn, n) if n else ():
                if short_queue and self.metric_sum is not None:
                    jax.block_until_ready(self.metric_sum)
                self.agent, metrics = programs.learn(self.agent, self.buffer, k)
                self.metric_sum = (
                    metrics
                    if self.metric_sum is None
                    else programs.add_metrics(self.metric_sum, metrics)
                )
                lv["metric_count"] += 1
            counters["updates"] += n
        self.state, ts = future.result()
        self.ts = hosts.to_global(ts)
        self._add(self.ts, action)
        self.returns = programs.accumulate(self.returns, self.ts)
        counters["iteration"] += 1
        # Frames count per seed over its envs (the mean over seeds where their envs differ).
        lv["env_steps"] += steps
        frames = lv["env_steps"] // len(self.lanes) * self.spec.action_repeat - counters["frame"]
        if frames:
            counters["frame"] += frames
            if pbar is not None:
                pbar.update(frames)
        ended = np.asarray(self.state.last)
        if ended.any():  # [2, S]: the summed returns and the number of the episodes each seed ended
            ended_returns = np.where(ended, hosts.read(self.returns), 0.0).sum(1)
            self.episode_returns.append(np.stack([ended_returns, ended.sum(1)]))
        ended_all = int(hosts.agree([ended.sum()]).sum())
        if ended_all:
            lv["episodes_ended"] += ended_all
            counters["episode"] = lv["episodes_ended"] // (ended.size * hosts.count)  # per env
            self._episodes_pending = True

    def _log(self, logger: RunLogger, pbar) -> None:
        config, counters, lv = self.config, self.counters, self.lv
        frame = counters["frame"]
        # Both reasons to log are the same on every process (a process whose lanes ended no
        # episode logs a row without a return).
        if frame < lv["next_log"] or not (lv["metric_count"] or self._episodes_pending):
            return
        self._episodes_pending = False
        now = time.perf_counter()
        row = {
            "episode": counters["episode"],
            "updates": counters["updates"],
            "fps": (frame - lv["last_log_frame"]) * len(self.lanes) / max(now - self._log_t, 1e-9),
        }
        if lv["metric_count"]:
            row.update(
                {k: self.hosts.read(v) / lv["metric_count"] for k, v in self.metric_sum.items()}
            )
            self.metric_sum, lv["metric_count"] = None, 0
        if self.episode_returns:
            total, count = np.sum(self.episode_returns, 0)
            with np.errstate(invalid="ignore", divide="ignore"):  # no episode ended: NaN
                row["episode_return"] = total / count
            self.episode_returns = []
        logger.write("train", frame, row)
        if pbar is not None:
            pbar.set_postfix_str(self._postfix(row["fps"]), refresh=False)
        # Detached runs (no bar) show this line on the console; with a bar only the file has it.
        log.info(
            "frame %d per seed: %.0f frames/s in all",
            frame,
            row["fps"],
            extra={"console": pbar is None},
        )
        self._log_t, lv["last_log_frame"] = now, frame
        lv["next_log"] = frame + config.log_every_frames

    def _postfix(self, fps) -> str:
        parts = [f"{fps:.0f} frames/s in all"] if np.isfinite(fps) else []
        if self.last_eval_return is not None:
            parts.append(f"eval return {self.last_eval_return:.1f}")
        return ", ".join(parts)

    def eval_due(self) -> bool:
        """An evaluation is due at this frame and has not started."""
        lv, frame = self.lv, self.counters["frame"]
        due = frame >= lv["next_eval"] or frame >= self.config.total_frames
        return due and lv["last_eval_frame"] != frame

    def _evaluate_if_due(self, wall_s, stop) -> None:
        """Start the evaluation due at this frame, if any: in a background thread on a copy of
        the parameters (`eval_in_background`, the default) while training goes on, or now. Its
        row is logged by `_finish_evaluations`, with the frame and wall time of its start.

        Background evaluations run one at a time, in order, and queue: the loop waits only when
        MAX_PENDING_EVALS are already started and not logged, so one evaluation that outlasts
        the training between two of them does not stall the loop. Each still evaluates the
        parameters of its own frame, on the eval env's next episodes, as it would unqueued."""
        self._finish_evaluations()
        config, lv, frame = self.config, self.lv, self.counters["frame"]
        if not self.eval_due() or stop:
            return
        background = self._eval_thread is not None
        self._finish_evaluations(keep=MAX_PENDING_EVALS - 1 if background else 0)
        # A copy: the loop donates the agent's buffers to its next update.
        params = jax.tree.map(jnp.copy, self.agent.params) if background else self.agent.params
        key = self._env_key(jax.random.fold_in(self.eval_root, frame))
        folder = self._workdir.resolve() / "videos"  # the evaluation process's too
        videos = [folder / f"eval_{frame}_{lane.name}.mp4" for lane in self.mine]

        def run():
            t0 = time.perf_counter()
            # A stop cuts short an evaluation that holds up the loop; those in the background
            # (or in their own process) run to their end first, so the checkpoint after them
            # holds their rows. A loop that fails ends those in this process (`_closing`).
            abort = (lambda: self._closing) if background else (lambda: bool(stop))
            metrics = self.evaluator.evaluate(
                params, key, videos=videos if config.save_video else None, stop=abort
            )
            return metrics, time.perf_counter() - t0

        pending = {"frame": frame, "wall_s": wall_s}
        if not background:  # what an aborted evaluation restores (the queue is empty here)
            pending["env_state"] = self.evaluator.host_state()
            pending["loop"] = {k: lv[k] for k in ("last_eval_frame", "next_eval")}
        lv["last_eval_frame"] = frame
        lv["next_eval"] = (frame // config.eval_every_frames + 1) * config.eval_every_frames
        if background:
            pending["future"] = self._eval_thread.submit(run)
        else:
            pending["future"] = future = concurrent.futures.Future()
            try:
                future.set_result(run())
            except EvalAborted as e:
                future.set_exception(e)
        self._pending_evals.append(pending)
        self._finish_evaluations(keep=None if background else 0)

    def _finish_evaluations(self, *, keep: int | None = None) -> None:
        """Log the evaluations that have ended, oldest first; with `keep`, first wait until at
        most `keep` are left unlogged."""
        queue = self._pending_evals
        while queue and (queue[0]["future"].done() or (keep is not None and len(queue) > keep)):
            self._log_evaluation(queue.popleft())

    def _log_evaluation(self, pending: dict) -> None:
        lv, frame = self.lv, pending["frame"]
        try:
            metrics, eval_s = pending["future"].result()
        except EvalAborted:  # the resumed run evaluates from here again
            self.evaluator.set_host_state(pending["env_state"])
            lv.update(pending["loop"])
            return
        fps_per_seed = frame / pending["wall_s"] if frame else np.nan  # nothing trained at 0
        metrics.update(
            wall_s=pending["wall_s"],
            eval_s=eval_s,
            fps=fps_per_seed * len(self.lanes),
            sec_per_1000_frames=1000.0 / fps_per_seed,
        )
        self._logger.write("eval", frame, metrics)
        self.last_eval_return = float(np.mean(metrics["episode_return"]))
        log.info(
            "eval @ %s frames: return per seed %s%s",
            f"{frame:,}",
            [round(float(r), 1) for r in metrics["episode_return"]],
            f", success per seed {np.round(metrics['success'], 2).tolist()}"
            if "success" in metrics
            else "",
        )
        if self._pbar is not None:
            self._pbar.set_postfix_str(self._postfix(metrics["fps"]))

    # -- the loop ----------------------------------------------------------------------------
    def loop(self, logger: RunLogger, workdir, stop: StopRequest) -> None:
        config, counters = self.config, self.counters
        ckpt_every = config.checkpoint_every_frames
        every = lambda n: (counters["frame"] // n + 1) * n  # noqa: E731
        next_ckpt = every(ckpt_every) if ckpt_every else None
        pbar = _pbar(config, config.total_frames, counters["frame"])
        self._logger, self._workdir, self._pbar = logger, pathlib.Path(workdir), pbar
        t_start, wall0 = time.perf_counter(), counters["wall_s"]
        self._log_t = t_start
        wall = lambda: wall0 + time.perf_counter() - t_start  # noqa: E731
        trace = _Trace(config.profile, self._workdir, counters["frame"])
        sync = lambda: jax.block_until_ready((self.agent, self.buffer, self.ts))  # noqa: E731
        try:
            # An evaluation a stop cut short runs first (the resumed run continues from there).
            self._evaluate_if_due(wall(), stop)
            # A checkpoint at an evaluation's frame is saved before that evaluation starts
            # (it holds it as due; a resumed run redoes it, with the same parameters): saving
            # never waits for an evaluation of its own frame, ~20 s on a GPU.
            while counters["frame"] < config.total_frames and not stop:
                trace.tick(counters["frame"], sync)
                self._step(pbar)
                self._log(logger, pbar)
                if next_ckpt is not None and counters["frame"] >= next_ckpt:
                    self.save(wall())
                    next_ckpt = every(ckpt_every)
                if counters["frame"] < config.total_frames:
                    self._evaluate_if_due(wall(), stop)
            if stop:
                log.warning(
                    "%s received: saving a checkpoint at frame %d per seed, then stopping",
                    stop.name,
                    counters["frame"],
                )
            trace.stop(sync)
            if self.ckpt.latest_step() != counters["frame"]:
                self.save(wall())
            self._evaluate_if_due(wall(), stop)  # the closing evaluation (none when stopped)
            self._finish_evaluations(keep=0)
            counters["wall_s"] = wall()
        finally:
            if self._eval_thread is not None:
                # After a failure, no evaluation in this process is left running on the env
                # the run closes next: it aborts at its next step. (The evaluation process's
                # `close` waits for the child instead.)
                self._closing = True
                local = isinstance(self.evaluator, LocalEvaluator)
                self._eval_thread.shutdown(wait=local, cancel_futures=True)
            if pbar is not None:
                pbar.close()
            trace.stop()  # a failing run's trace, without waiting on its arrays


def _best(values: np.ndarray) -> float:
    """The largest non-NaN value; NaN when there is none (a run stopped before evaluating)."""
    return float(np.nanmax(values)) if np.isfinite(values).any() else math.nan


def _distraction_line(spec: envs.EnvSpec) -> str:
    """What the run's frames were distracted by, as the summary says it."""
    if spec.distraction == "none":
        return "no distraction"
    kinds = ", ".join(spec.distraction_types)
    return (
        f"distraction {spec.distraction} ({kinds}; {'dynamic' if spec.dynamic else 'static'}; "
        f"backgrounds: {spec.backgrounds})"
    )


def write_summary(
    workdir,
    config,
    spec,
    counters,
    *,
    devices: int = 1,
    stopped: str | None = None,
    evaluated_on: str,
) -> dict:
    """Summary per seed from the eval logs, saved as summary.md / summary.json and printed
    unless the run was `stopped` (by that signal's name) before its end. `evaluated_on`: the
    resolved eval_device."""
    wall = counters["wall_s"]
    runs = lanes.lanes(config)
    fps = counters["frame"] * len(runs) / max(wall, 1e-9)
    rows, per_seed = [], []
    for lane in runs:
        path = workdir / lane.name / "eval.csv"
        evals = read_csv(path) if path.exists() else {}
        returns = evals.get("episode_return", np.array([np.nan]))
        abs_cos = evals.get("abs_cos_agent_env", np.array([np.nan]))
        cos = evals.get("cos_agent_env", np.array([np.nan]))
        best = _best(returns)
        per_seed.append(
            dict(
                seed=lane.seed,
                lane=lane.name,
                settings=dict(lane.settings),
                final_return=float(returns[-1]),
                best_return=best,
                cos_agent_env=float(cos[-1]),
                abs_cos_agent_env=float(abs_cos[-1]),
            )
        )
        rows.append([lane.name, f"{returns[-1]:.1f}", f"{best:.1f}", f"{abs_cos[-1]:.2e}"])
        if spec.has_success:  # success rate of the eval episodes (kitchen)
            success = evals.get("success", np.array([np.nan]))
            per_seed[-1].update(final_success=float(success[-1]), best_success=_best(success))
            rows[-1].append(f"{success[-1]:.2f}")
    for label in dict.fromkeys(lane.label for lane in runs):  # mean over each setting's seeds
        group = [p for p, lane in zip(per_seed, runs) if lane.label == label]
        finals = np.array([p["final_return"] for p in group])
        rows.append([f"mean {label}".strip(), f"{finals.mean():.1f} ± {finals.std():.1f}", "", ""])
        if spec.has_success:
            rates = np.array([p["final_success"] for p in group])
            rows[-1].append(f"{rates.mean():.2f} ± {rates.std():.2f}")
    summary = {
        "task": config.env.task,
        "method": config.agent.method,
        "action_dim": spec.action_dim,
        "seeds": config.seeds,
        "lanes": len(runs),
        "sweep": {k: list(v) for k, v in lanes.sweep_values(config).items()},
        "devices": devices,
        "processes": jax.process_count(),
        "envs_per_seed": config.envs_per_seed,
        "frames_per_seed": counters["frame"],
        "updates_per_seed": counters["updates"],
        "wall_s": wall,
        "aggregate_fps": fps,
        "backend": spec.backend,
        "device": jax.devices()[0].device_kind,
        "conv_stack": networks.stack_for(config.agent.conv_stack),
        "render": config.env.render.to_dict(),
        "render_quality": config.env.render.quality,
        "eval_device": evaluated_on,
        "distraction": config.env.distraction,
        "distraction_types": list(spec.distraction_types),
        "backgrounds": spec.backgrounds,
        "stopped": stopped,
        "per_seed": per_seed,
        "provenance": provenance(),
    }
    unit = "lane" if runs[0].settings else "seed"
    columns = [unit, "final eval return", "best eval return", "abs cos(z_A, z_E)"]
    columns += ["final eval success"] if spec.has_success else []
    table = format_table(columns, rows)
    until = f"stopped by {stopped} at " if stopped else ""
    text = (
        f"# {config.agent.method} on {config.env.task}\n\n"
        f"{until}{counters['frame']:,} frames per {unit} x {len(runs)} {unit}s, "
        f"{wall:.0f} s of training ({fps:.0f} frames/s in all) on {summary['device']} "
        f"({spec.backend} physics, {summary['conv_stack']} conv stacks, evaluations on "
        f"{summary['eval_device']}); {_distraction_line(spec)}; render "
        f"settings {summary['render']}; commit {summary['provenance']['commit']}, jax "
        f"{summary['provenance']['jax']}\n\n{table}\n"
    )
    write_text_atomic(workdir / "summary.md", text)
    write_text_atomic(workdir / "summary.json", json.dumps(summary, indent=1))
    if not stopped:
        print(text)
    return summary
