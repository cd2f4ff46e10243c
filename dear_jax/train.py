"""The training loop: S seeds as a vmapped axis, E environments per seed, one process.

One iteration (DESIGN.md): act for every seed and env on the accelerator -> dispatch physics ->
dispatch E / update_every_steps updates per seed while a background thread renders the new
observations on CPU workers -> add the new timestep to each seed's replay. The only host syncs in
the loop are the physics state crossing to the renderers and, once per episode or log interval,
a few scalars for the logs.

`train(config, workdir)` runs (or resumes) a whole experiment and returns its summary.
"""

from __future__ import annotations

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
from dear_jax.logger import RunLogger, format_table
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
    """The jitted functions of the loop, all vmapped over seeds."""

    act: callable  # (agent, obs [S,E,...], key) -> (actions [S,E,A], agent)
    learn: callable  # (agent, replay, key, num_updates) -> (agent, metrics [S])
    add: callable  # (replay, ts, action) -> replay
    evaluate_step: callable  # (agent, obs) -> (actions, cos [S], predicted mask of env 0 [S,H,W])
    accumulate: callable  # (returns [S,E], ts) -> returns


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

    def learn(agent, buffer, key, num_updates):
        def body(agent, k):
            return jax.vmap(learn_one)(agent, buffer, jax.random.split(k, num_seeds), hp)

        agent, metrics = jax.lax.scan(body, agent, jax.random.split(key, num_updates))
        return agent, jax.tree.map(lambda m: m.mean(0), metrics)

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
        learn=jax.jit(learn, static_argnums=3, donate_argnums=0),
        add=jax.jit(add, donate_argnums=0),
        evaluate_step=jax.jit(evaluate_step),
        accumulate=jax.jit(accumulate),
    )


def evaluate(env: envs.Env, programs: Programs, agent, key, *, video: bool) -> tuple[dict, dict]:
    """One episode in each of the eval env's E envs per seed, deterministic actions.

    Returns per-seed metrics ([S] arrays) and, if asked, video frames of env 0 per seed.
    """
    state, ts = env.reset(key)
    returns = jnp.zeros(env.shape)
    success = jnp.zeros(env.shape)
    cos_sum, steps = jnp.zeros(env.shape[0]), 0
    frames = []
    while True:
        action, cos, pred = programs.evaluate_step(agent, ts.obs)
        if video:
            frames.append((ts.frame[:, 0], ts.true_mask[:, 0], pred))
        cos_sum, steps = cos_sum + cos, steps + 1
        if bool(np.all(state.last)):
            break
        state, ts = env.step(state, action)
        returns = returns + ts.reward
        success = jnp.maximum(success, ts.success)
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
    num_seeds, num_envs = config.seeds, config.envs_per_seed
    a = config.agent

    env = make_env(config, envs_per_seed=num_envs, split="train", seed=config.seed)
    spec = env.spec
    replay.check_fits(num_seeds, config.replay.capacity, spec.frame_shape, spec.action_dim)
    acfg = agent_config(config, spec.action_dim)
    hp = hparams(config).for_seeds(num_seeds)
    programs = build_programs(acfg, hp, config)

    root = jax.random.key(config.seed)
    seed_keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(num_seeds))
    agent = jax.jit(jax.vmap(functools.partial(update.init, acfg)))(seed_keys)
    buffer = replay.init(
        config.replay.capacity, num_envs, spec.frame_shape, spec.action_dim, leading=(num_seeds,)
    )
    key = jax.random.fold_in(root, 1_000_003)
    counters = {"frame": 0, "iteration": 0, "episode": 0, "updates": 0, "wall_s": 0.0}

    ckpt = Checkpointer(
        workdir / "checkpoints", fingerprint=_fingerprint(config), keep=config.keep_checkpoints
    )
    resumed_from = None
    if ckpt.latest_step() is not None:
        template = {"agent": agent, "key": jax.random.key_data(key)}
        if config.save_replay:
            template["replay"] = buffer
        step, restored, counters = ckpt.restore(template)
        agent, key = restored["agent"], jax.random.wrap_key_data(restored["key"])
        buffer = restored.get("replay", buffer)
        resumed_from = counters["frame"]
        log.info("resumed from frame %d (checkpoint %d)", resumed_from, step)
    (workdir / "config.json").write_text(config.to_json(indent=1))

    logger = RunLogger(workdir, num_seeds, resume_frame=resumed_from)
    eval_env = make_env(
        config, envs_per_seed=config.num_eval_episodes, split="val", seed=config.seed + 1
    )
    frames_per_row = spec.action_repeat  # frames per seed per env step of one env
    seed_frames = config.replay.seed_frames
    if resumed_from is not None and not config.save_replay:
        seed_frames = resumed_from + config.replay.seed_frames  # refill an empty replay first
    next_eval = (counters["frame"] // config.eval_every_frames + 1) * config.eval_every_frames
    next_log = counters["frame"] + config.log_every_frames
    ckpt_every = config.checkpoint_every_frames
    next_ckpt = (counters["frame"] // ckpt_every + 1) * ckpt_every if ckpt_every else None

    eval_history = []
    key, k_reset = jax.random.split(key)
    state, ts = env.reset(k_reset)
    buffer = programs.add(buffer, ts, jnp.zeros((num_seeds, num_envs, spec.action_dim)))
    returns = jnp.zeros((num_seeds, num_envs))
    metric_sum, metric_count = None, 0
    episode_returns = []
    pbar = _pbar(config, config.total_frames, counters["frame"])
    steps_owed = 0.0  # agent steps per seed not yet matched by updates
    t_start, wall0 = time.perf_counter(), counters["wall_s"]
    last_log_t, last_log_frame = t_start, counters["frame"]

    def save(frame):
        tree = {"agent": agent, "key": jax.random.key_data(key)}
        if config.save_replay:
            tree["replay"] = buffer
        counters["wall_s"] = wall0 + time.perf_counter() - t_start
        ckpt.save(frame, tree, extra=dict(counters))

    try:
        while counters["frame"] < config.total_frames:
            key, k_act, k_learn = jax.random.split(key, 3)
            action, agent = programs.act(agent, ts.obs, k_act)
            reset = np.asarray(state.last)
            future = env.step_async(state, action)
            if counters["frame"] >= seed_frames:
                steps_owed += num_envs / a.update_every_steps
                n = int(steps_owed)
                if n:
                    steps_owed -= n
                    agent, metrics = programs.learn(agent, buffer, k_learn, n)
                    counters["updates"] += n
                    metric_sum = (
                        metrics
                        if metric_sum is None
                        else jax.tree.map(jnp.add, metric_sum, metrics)
                    )
                    metric_count += 1
            state, ts = future.result()
            buffer = programs.add(buffer, ts, action)
            returns = programs.accumulate(returns, ts)
            counters["iteration"] += 1
            if not reset.all():
                counters["frame"] += frames_per_row
                if pbar is not None:
                    pbar.update(frames_per_row)
            if state.last.all():
                counters["episode"] += 1
                episode_returns.append(np.asarray(returns).mean(1))

            frame = counters["frame"]
            if frame >= next_log and (metric_count or episode_returns):
                now = time.perf_counter()
                fps = (frame - last_log_frame) * num_seeds / max(now - last_log_t, 1e-9)
                row = {
                    "episode": counters["episode"],
                    "updates": counters["updates"],
                    "fps": fps,
                    "buffer_size": float(np.asarray(buffer.size[0])) * num_envs,
                }
                if metric_count:
                    row.update({k: np.asarray(v) / metric_count for k, v in metric_sum.items()})
                    metric_sum, metric_count = None, 0
                if episode_returns:
                    row["episode_return"] = np.mean(episode_returns, 0)
                    episode_returns = []
                logger.write("train", frame, row)
                if pbar is not None:
                    pbar.set_postfix(
                        fps=f"{fps:.0f}", ret=f"{np.mean(row.get('episode_return', np.nan)):.1f}"
                    )
                last_log_t, last_log_frame = now, frame
                next_log = frame + config.log_every_frames
            if frame >= next_eval or frame >= config.total_frames:
                key, k_eval = jax.random.split(key)
                t_eval = time.perf_counter()
                metrics, clips = evaluate(
                    eval_env, programs, agent, k_eval, video=config.save_video
                )
                wall = wall0 + time.perf_counter() - t_start
                metrics.update(
                    wall_s=wall,
                    eval_s=time.perf_counter() - t_eval,
                    fps=frame * num_seeds / max(wall, 1e-9),
                    sec_per_1000_frames=1000.0 / max(frame / max(wall, 1e-9), 1e-9),
                )
                logger.write("eval", frame, metrics)
                eval_history.append((frame, metrics))
                for s, clip in clips.items():
                    write_video(workdir / "videos" / f"eval_{frame}_seed{s}.mp4", clip, fps=30)
                if pbar is not None:
                    pbar.write(
                        f"eval @ {frame} frames: return per seed "
                        f"{np.round(metrics['episode_return'], 1).tolist()}"
                    )
                next_eval = (frame // config.eval_every_frames + 1) * config.eval_every_frames
            if next_ckpt is not None and frame >= next_ckpt:
                save(frame)
                next_ckpt = (frame // ckpt_every + 1) * ckpt_every
        save(counters["frame"])
    finally:
        if pbar is not None:
            pbar.close()
        logger.close()
        ckpt.close()
        env.close()
        eval_env.close()
    return write_summary(workdir, config, spec, counters, eval_history)


def write_summary(workdir, config, spec, counters, eval_history) -> dict:
    """Summary table per seed (printed, and saved as summary.md / summary.json)."""
    wall = counters["wall_s"]
    fps = counters["frame"] * config.seeds / max(wall, 1e-9)
    rows, per_seed = [], []
    for s in range(config.seeds):
        returns = [float(m["episode_return"][s]) for _, m in eval_history]
        final = returns[-1] if returns else float("nan")
        best = max(returns) if returns else float("nan")
        cos = float(eval_history[-1][1]["cos_agent_env"][s]) if eval_history else float("nan")
        per_seed.append(dict(seed=s, final_return=final, best_return=best, cos_agent_env=cos))
        rows.append([s, f"{final:.1f}", f"{best:.1f}", f"{cos:.2e}"])
    finals = np.array([p["final_return"] for p in per_seed])
    rows.append(["mean", f"{finals.mean():.1f} ± {finals.std():.1f}", "", ""])
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
    table = format_table(["seed", "final eval return", "best eval return", "cos(z_A, z_E)"], rows)
    text = (
        f"# {config.agent.method} on {config.env.task}\n\n"
        f"{counters['frame']:,} frames per seed x {config.seeds} seeds in {wall:.0f} s "
        f"({fps:.0f} frames/s in all) on {summary['device']} ({spec.backend} physics); "
        f"render settings {summary['render']}\n\n{table}\n"
    )
    (workdir / "summary.md").write_text(text)
    (workdir / "summary.json").write_text(json.dumps(summary, indent=1))
    print(text)
    return summary
