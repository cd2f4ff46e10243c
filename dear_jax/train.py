"""The training loop: S seeds as a vmapped axis, E environments per seed, one process.

One iteration (DESIGN.md): act for every seed and env on the accelerator -> dispatch physics ->
dispatch E / update_every_steps updates per seed while a background thread renders the new
observations on CPU workers -> add the new timestep to each seed's replay. The only host syncs in
the loop are the physics state crossing to the renderers and, once per episode or log interval,
a few scalars for the logs.

`train(config, workdir)` runs (or resumes) a whole experiment and returns its summary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from ml_collections import ConfigDict

import envs
from dear_jax import losses, replay, update
from dear_jax.checkpoint import Checkpointer
from dear_jax.logger import RunLogger, format_table, read_csv
from dear_jax.video import side_by_side, write_video

log = logging.getLogger("dear_jax")

# Config fields that must match for a checkpoint to be resumed.
FINGERPRINT_KEYS = (
    "seed",
    "seeds",
    "envs_per_seed",
    "env.task",
    "env.action_repeat",
    "agent.method",
    "agent.encoder",
    "agent.latent_dim",
    "agent.feature_dim",
    "agent.hidden_dim",
    "replay.capacity",
)


def _get(config: ConfigDict, dotted: str):
    for part in dotted.split("."):
        config = config[part]
    return config


def validate(config: ConfigDict) -> None:
    """Fail early, naming the field and the valid choices."""
    if config.env.task not in envs.names():
        raise ValueError(f"unknown env.task {config.env.task!r}; valid: {', '.join(envs.names())}")
    choices = {
        "agent.method": update.METHODS,
        "agent.encoder": ("pool", "plain"),
        "agent.ortho_form": losses.ORTHOGONALITY_FORMS,
        "agent.seed_axis": update.SEED_AXES,
        "env.backend": ("auto", "mjx", "cpu"),
        "env.distraction": ("none", "easy", "medium", "hard"),
        "env.mask": ("true", "noisy", "approximate"),
    }
    for key, valid in choices.items():
        if _get(config, key) not in valid:
            raise ValueError(f"unknown {key} {_get(config, key)!r}; valid: {', '.join(valid)}")
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
    )


def hparams(config: ConfigDict) -> update.HParams:
    a = config.agent
    names = [f.name for f in dataclasses.fields(update.HParams)]
    return update.HParams(**{n: float(a[n]) for n in names})


def make_env(config: ConfigDict, *, envs_per_seed: int, split: str, seed: int) -> envs.Env:
    e = config.env
    env = envs.make(
        e.task,
        num_seeds=config.seeds,
        envs_per_seed=envs_per_seed,
        backend=e.backend,
        distraction=e.distraction,
        dynamic=e.dynamic,
        background_dir=e.background_dir or None,
        split=split,
        mask=e.mask,
        mask_drop_prob=e.mask_drop_prob,
        render=envs.RenderSettings(**e.render.to_dict()),
        seed=seed,
        action_repeat=e.action_repeat,
        episode_frames=e.episode_frames or None,
    )
    return env


@dataclasses.dataclass(frozen=True)
class Programs:
    """The jitted functions of the loop, each over all seeds at once."""

    act: callable  # (agent, obs [S,E,...], key) -> (actions [S,E,A], agent)
    learn: callable  # (agent, replay, key) -> (agent, metrics [S]): one update per seed
    add: callable  # (replay, ts, action) -> replay
    evaluate_step: callable  # (agent, obs) -> (actions, cos [S], predicted mask of env 0 [S,H,W])
    accumulate: callable  # (returns [S,E], ts) -> returns
    add_metrics: callable  # (metrics, metrics) -> elementwise sum


def build_programs(acfg: update.AgentConfig, hp: update.HParams, config: ConfigDict) -> Programs:
    a = config.agent
    num_seeds = config.seeds
    nets = update.make_networks(acfg)

    def act(agent, obs, key):
        keys = jax.random.split(key, num_seeds)
        per_seed = functools.partial(update.act, acfg, explore=True)
        return jax.vmap(per_seed)(agent, obs, keys, hp)

    def learn_one(agent, buffer, key, hp_seed):
        k_sample, k_update = jax.random.split(key)
        batch = replay.sample(
            buffer,
            k_sample,
            a.batch_size,
            nstep=a.nstep,
            gamma=a.discount,
            frame_stack=acfg.frame_stack,
            far_max=a.ted_far_max if acfg.method == "ted" else 0,
        )
        return update.update(agent, batch, k_update, hp_seed, cfg=acfg)

    # One update per seed per call; the loop calls it E / update_every_steps times (dispatch is
    # asynchronous). A lax.scan over the updates made tests/test_run.py's tiny runs ~3x slower
    # on CPU (its fixture: 298 s with the scan, 97 s without; pytest --durations).
    def learn(agent, buffer, key):
        keys = jax.random.split(key, num_seeds)
        return update.over_seeds(learn_one, a.seed_axis)(agent, buffer, keys, hp)

    def add(buffer, ts, action):
        return jax.vmap(replay.add)(
            buffer, ts.frame, ts.mask, action, ts.reward, ts.discount, ts.first
        )

    def evaluate_step(agent, obs):
        def one(agent, obs):
            z = nets.encoder.apply({"params": agent.params["encoder"]}, obs)
            action = nets.actor.apply({"params": agent.params["actor"]}, z)
            z_env, z_agent = losses.split_latent(z)
            cos = jnp.mean(losses.cosine_similarity(z_agent, z_env))
            if nets.mask_decoder is None:
                pred = jnp.zeros(obs.shape[1:3])
            else:  # newest frame's channel of env 0
                logits = nets.mask_decoder.apply(
                    {"params": agent.params["mask_decoder"]}, z_agent[:1]
                )
                pred = jax.nn.sigmoid(logits[0, ..., -1])
            return action, cos, pred

        return jax.vmap(one)(agent, obs)

    def accumulate(returns, ts):
        return jnp.where(ts.first, 0.0, returns) + ts.reward

    return Programs(
        act=jax.jit(act, donate_argnums=0),
        learn=jax.jit(learn, donate_argnums=0),
        add=jax.jit(add, donate_argnums=0),
        evaluate_step=jax.jit(evaluate_step),
        accumulate=jax.jit(accumulate),
        add_metrics=jax.jit(lambda a, b: jax.tree.map(jnp.add, a, b)),
    )


def evaluate(env: envs.Env, programs: Programs, agent, key, *, video: bool) -> tuple[dict, dict]:
    """One episode in each of the eval env's E envs per seed, deterministic actions.

    Returns per-seed metrics ([S] arrays) and, if asked, video frames of env 0 per seed.
    """
    state, ts = env.reset(key)
    returns = jnp.zeros(env.shape)
    success = jnp.zeros(env.shape)
    done = np.zeros(env.shape, bool)  # envs whose first episode has ended (kitchen: at success)
    cos_sum, steps = jnp.zeros(env.shape[0]), 0
    frames = []
    while True:
        action, cos, pred = programs.evaluate_step(agent, ts.obs)
        if video:
            frames.append((ts.frame[:, 0], ts.true_mask[:, 0], pred))
        cos_sum, steps = cos_sum + cos, steps + 1
        done |= np.asarray(state.last)
        if done.all():
            break
        live = jnp.asarray(~done)  # an ended env restarts; its next episode does not count
        state, ts = env.step(state, action)
        returns = returns + jnp.where(live, ts.reward, 0.0)
        success = jnp.maximum(success, jnp.where(live, ts.success, 0.0))
    metrics = {
        "episode_return": np.asarray(returns.mean(1)),
        "cos_agent_env": np.asarray(cos_sum / steps),
    }
    if env.spec.has_success:
        metrics["success"] = np.asarray(success.mean(1))
    clips = {}
    if video:
        rgb, true_mask, pred = (np.asarray(jnp.stack(x, 1)) for x in zip(*frames))
        clips = {s: side_by_side(rgb[s], true_mask[s], pred[s]) for s in range(rgb.shape[0])}
    return metrics, clips


def _fingerprint(config: ConfigDict) -> dict:
    return {k: _get(config, k) for k in FINGERPRINT_KEYS}


def _pbar(config, total, initial):
    if not config.progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="frame", desc="frames per seed", smoothing=0.05)


def train(config: ConfigDict, workdir: str | pathlib.Path) -> dict:
    """Run (or resume) the experiment described by `config` in `workdir`; returns the summary."""
    validate(config)
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        env = stack.enter_context(
            make_env(config, envs_per_seed=config.envs_per_seed, split="train", seed=config.seed)
        )
        spec = env.spec
        replay.check_fits(config.seeds, config.replay.capacity, spec.frame_shape, spec.action_dim)
        ckpt = Checkpointer(
            workdir / "checkpoints", fingerprint=_fingerprint(config), keep=config.keep_checkpoints
        )
        stack.callback(ckpt.close)
        run = _Run(config, spec, ckpt)
        (workdir / "config.json").write_text(config.to_json(indent=1))
        logger = RunLogger(workdir, config.seeds, resume_frame=run.resumed_from)
        stack.callback(logger.close)
        eval_env = stack.enter_context(
            make_env(
                config, envs_per_seed=config.num_eval_episodes, split="val", seed=config.seed + 1
            )
        )
        run.loop(env, eval_env, logger, workdir)
    return write_summary(workdir, config, spec, run.counters)


class _Run:
    """The mutable state of one training run on the host side: agent, replay, keys, counters."""

    def __init__(self, config: ConfigDict, spec: envs.EnvSpec, ckpt: Checkpointer):
        self.config, self.spec, self.ckpt = config, spec, ckpt
        num_seeds = config.seeds
        self.acfg = agent_config(config, spec.action_dim)
        self.programs = build_programs(self.acfg, hparams(config).for_seeds(num_seeds), config)
        root = jax.random.key(config.seed)
        seed_keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(num_seeds))
        self.agent = jax.jit(functools.partial(update.init_seeds, self.acfg))(seed_keys)
        self.buffer = replay.init(
            config.replay.capacity,
            config.envs_per_seed,
            spec.frame_shape,
            spec.action_dim,
            leading=(num_seeds,),
        )
        self.key = jax.random.fold_in(root, 1_000_003)
        self.counters = {"frame": 0, "iteration": 0, "episode": 0, "updates": 0, "wall_s": 0.0}
        self.resumed_from = None
        if ckpt.latest_step() is not None:
            step, restored, self.counters = ckpt.restore(self._tree())
            self.agent = restored["agent"]
            self.key = jax.random.wrap_key_data(restored["key"])
            self.buffer = restored.get("replay", self.buffer)
            self.resumed_from = self.counters["frame"]
            log.info("resumed from frame %d (checkpoint %d)", self.resumed_from, step)

    def _tree(self) -> dict:
        tree = {"agent": self.agent, "key": jax.random.key_data(self.key)}
        if self.config.save_replay:
            tree["replay"] = self.buffer
        return tree

    def save(self, wall_s: float) -> None:
        self.counters["wall_s"] = wall_s
        self.ckpt.save(self.counters["frame"], self._tree(), extra=dict(self.counters))

    def loop(self, env: envs.Env, eval_env: envs.Env, logger: RunLogger, workdir) -> None:
        config, spec, programs, counters = self.config, self.spec, self.programs, self.counters
        num_seeds, num_envs = config.seeds, config.envs_per_seed
        # Frames count per seed, summed over its E envs (as in DrQ-v2 with one env per seed): one
        # loop iteration is E agent steps and E x action_repeat frames of every seed.
        frames_per_step = num_envs * spec.action_repeat
        seed_frames = config.replay.seed_frames
        if self.resumed_from is not None and not config.save_replay:
            seed_frames += self.resumed_from  # refill the empty replay before updating again
        every = lambda n: (counters["frame"] // n + 1) * n  # noqa: E731
        next_eval = every(config.eval_every_frames)
        next_log = counters["frame"] + config.log_every_frames
        ckpt_every = config.checkpoint_every_frames
        next_ckpt = every(ckpt_every) if ckpt_every else None

        self.key, k_reset = jax.random.split(self.key)
        state, ts = env.reset(k_reset)
        self.buffer = programs.add(
            self.buffer, ts, jnp.zeros((num_seeds, num_envs, spec.action_dim))
        )
        returns = jnp.zeros((num_seeds, num_envs))
        metric_sum, metric_count, episode_returns = None, 0, []
        steps_owed = 0.0  # agent steps per seed not yet matched by updates
        pbar = _pbar(config, config.total_frames, counters["frame"])
        t_start, wall0 = time.perf_counter(), counters["wall_s"]
        last_log_t, last_log_frame = t_start, counters["frame"]
        wall = lambda: wall0 + time.perf_counter() - t_start  # noqa: E731
        try:
            while counters["frame"] < config.total_frames:
                self.key, k_act, k_learn = jax.random.split(self.key, 3)
                action, self.agent = programs.act(self.agent, ts.obs, k_act)
                stepped = not np.asarray(state.last).all()  # all envs reset after a last step
                future = env.step_async(state, action)
                # Updates are dispatched while the env thread renders the next observations;
                # a reset step adds no transition, so it owes no update.
                if counters["frame"] >= seed_frames and stepped:
                    steps_owed += num_envs / config.agent.update_every_steps
                    n = int(steps_owed)
                    steps_owed -= n
                    for k in jax.random.split(k_learn, n) if n else ():
                        self.agent, metrics = programs.learn(self.agent, self.buffer, k)
                        metric_sum = (
                            metrics
                            if metric_sum is None
                            else programs.add_metrics(metric_sum, metrics)
                        )
                        metric_count += 1
                    counters["updates"] += n
                state, ts = future.result()
                self.buffer = programs.add(self.buffer, ts, action)
                returns = programs.accumulate(returns, ts)
                counters["iteration"] += 1
                if stepped:  # a reset step shows the first frames; it is not a step
                    counters["frame"] += frames_per_step
                    if pbar is not None:
                        pbar.update(frames_per_step)
                if state.last.all():
                    counters["episode"] += 1
                    episode_returns.append(np.asarray(returns).mean(1))

                frame = counters["frame"]
                if frame >= next_log and (metric_count or episode_returns):
                    now = time.perf_counter()
                    row = {
                        "episode": counters["episode"],
                        "updates": counters["updates"],
                        "fps": (frame - last_log_frame) * num_seeds / max(now - last_log_t, 1e-9),
                    }
                    if metric_count:
                        row.update({k: np.asarray(v) / metric_count for k, v in metric_sum.items()})
                        metric_sum, metric_count = None, 0
                    if episode_returns:
                        row["episode_return"] = np.mean(episode_returns, 0)
                        episode_returns = []
                    logger.write("train", frame, row)
                    if pbar is not None:
                        pbar.set_postfix(fps=f"{row['fps']:.0f}")
                    else:  # detached runs: a line per log interval instead of the bar
                        log.info("frame %d per seed: %.0f frames/s in all", frame, row["fps"])
                    last_log_t, last_log_frame = now, frame
                    next_log = frame + config.log_every_frames
                if frame >= next_eval or frame >= config.total_frames:
                    self._evaluate(eval_env, logger, workdir, frame, wall(), pbar)
                    next_eval = every(config.eval_every_frames)
                if next_ckpt is not None and frame >= next_ckpt:
                    self.save(wall())
                    next_ckpt = every(ckpt_every)
            if self.ckpt.latest_step() != counters["frame"]:
                self.save(wall())
            counters["wall_s"] = wall()
        finally:
            if pbar is not None:
                pbar.close()

    def _evaluate(self, eval_env, logger, workdir, frame, wall_s, pbar) -> None:
        config = self.config
        self.key, k_eval = jax.random.split(self.key)
        t0 = time.perf_counter()
        metrics, clips = evaluate(
            eval_env, self.programs, self.agent, k_eval, video=config.save_video
        )
        fps_per_seed = frame / max(wall_s, 1e-9)
        metrics.update(
            wall_s=wall_s,
            eval_s=time.perf_counter() - t0,
            fps=fps_per_seed * config.seeds,
            sec_per_1000_frames=1000.0 / max(fps_per_seed, 1e-9),
        )
        logger.write("eval", frame, metrics)
        for s, clip in clips.items():
            write_video(workdir / "videos" / f"eval_{frame}_seed{s}.mp4", clip, fps=30)
        message = (
            f"eval @ {frame:,} frames: return per seed "
            f"{np.round(metrics['episode_return'], 1).tolist()}"
        )
        if "success" in metrics:
            message += f", success per seed {np.round(metrics['success'], 2).tolist()}"
        (pbar.write if pbar is not None else log.info)(message)


def write_summary(workdir, config, spec, counters) -> dict:
    """Summary per seed from the eval logs (printed, and saved as summary.md / summary.json)."""
    wall = counters["wall_s"]
    fps = counters["frame"] * config.seeds / max(wall, 1e-9)
    rows, per_seed = [], []
    for s in range(config.seeds):
        path = workdir / f"seed_{s}" / "eval.csv"
        evals = read_csv(path) if path.exists() else {}
        returns = evals.get("episode_return", np.array([np.nan]))
        cos = evals.get("cos_agent_env", np.array([np.nan]))
        per_seed.append(
            dict(
                seed=s,
                final_return=float(returns[-1]),
                best_return=float(np.nanmax(returns)),
                cos_agent_env=float(cos[-1]),
            )
        )
        rows.append([s, f"{returns[-1]:.1f}", f"{np.nanmax(returns):.1f}", f"{cos[-1]:.2e}"])
        if spec.has_success:  # success rate of the eval episodes (kitchen)
            success = evals.get("success", np.array([np.nan]))
            per_seed[-1].update(
                final_success=float(success[-1]), best_success=float(np.nanmax(success))
            )
            rows[-1].append(f"{success[-1]:.2f}")
    finals = np.array([p["final_return"] for p in per_seed])
    rows.append(["mean", f"{finals.mean():.1f} ± {finals.std():.1f}", "", ""])
    if spec.has_success:
        rates = np.array([p["final_success"] for p in per_seed])
        rows[-1].append(f"{rates.mean():.2f} ± {rates.std():.2f}")
    summary = {
        "task": config.env.task,
        "method": config.agent.method,
        "seeds": config.seeds,
        "envs_per_seed": config.envs_per_seed,
        "frames_per_seed": counters["frame"],
        "updates_per_seed": counters["updates"],
        "wall_s": wall,
        "aggregate_fps": fps,
        "backend": spec.backend,
        "device": jax.devices()[0].device_kind,
        "render": config.env.render.to_dict(),
        "distraction": config.env.distraction,
        "per_seed": per_seed,
    }
    columns = ["seed", "final eval return", "best eval return", "cos(z_A, z_E)"]
    columns += ["final eval success"] if spec.has_success else []
    table = format_table(columns, rows)
    text = (
        f"# {config.agent.method} on {config.env.task}\n\n"
        f"{counters['frame']:,} frames per seed x {config.seeds} seeds, {wall:.0f} s of training "
        f"({fps:.0f} frames/s in all) on {summary['device']} ({spec.backend} physics); "
        f"render settings {summary['render']}\n\n{table}\n"
    )
    (workdir / "summary.md").write_text(text)
    (workdir / "summary.json").write_text(json.dumps(summary, indent=1))
    print(text)
    return summary
