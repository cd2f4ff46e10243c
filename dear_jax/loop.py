"""The training loop: its iteration (`Loop.step`), its checkpoints (`Loop.save`, and the restore
a resumed run starts from) and the loop itself (`Loop.run`).

One iteration (docs/design.md): act for every seed and env on the accelerator -> hand the
actions to the env (CPU physics steps on its thread; MJX physics is dispatched) -> dispatch
E / update_every_steps updates per seed while the env thread renders the new observations on CPU
workers -> add the new timestep to each seed's replay. The main thread waits on the accelerator
only once per episode or log interval (a few scalars for the logs) and, while an evaluation runs
in the background, for each update before dispatching the next; the env thread waits for the
actions (CPU physics) or the physics state (MJX) it needs. Evaluations in the background queue
up to `evaluations.MAX_PENDING_EVALS` deep, one more per further evaluation process.
"""

from __future__ import annotations

import functools
import logging
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from ml_collections import ConfigDict

import envs
from dear_jax import lanes, replay, replay_disk, update
from dear_jax.carry import Carry
from dear_jax.checkpoint import Checkpointer, UnreadableCheckpointError
from dear_jax.devices import Hosts, seed_sharding, uncommitted
from dear_jax.evaluations import Evaluations, eval_due
from dear_jax.evaluator import EvalProcess, EvalProcesses, LocalEvaluator
from dear_jax.experiment import agent_config, updates_per_call
from dear_jax.logger import RunLogger
from dear_jax.programs import cached_programs, hold_keys
from dear_jax.progress import Progress, TrainLog
from dear_jax.signals import before_training
from dear_jax.trace import Trace

log = logging.getLogger("dear_jax")

_init_seeds = jax.jit(update.init_seeds, static_argnums=0)


def replay_rows_kept(ckpt: Checkpointer, rows: int) -> set[int] | None:
    """Row counts, up to `rows`, of the kept checkpoints whose replay is on disk: the replay files
    each needs to resume. A checkpoint saved without the replay on disk (before a resume restarted
    the row count) is not one of them. None where a kept checkpoint's metadata cannot be read:
    which files it needs is unknown, so none may be deleted; it is named in a warning, and the
    save that asks goes on."""
    kept = set()
    for step in ckpt.all_steps():
        try:
            extra = ckpt.read_meta(step)[2]
        except UnreadableCheckpointError as e:
            log.warning("%s. No replay file is deleted while it is kept", e)
            return None
        if extra.get("replay_on_disk") and extra["counters"]["rows"] <= rows:
            kept.add(extra["counters"]["rows"])
    return kept


class Loop:
    """One training run on this process: its programs, its `carry` (fresh, or restored from the
    latest checkpoint in `ckpt`), its envs and its evaluator."""

    def __init__(
        self,
        config: ConfigDict,
        spec: envs.EnvSpec,
        ckpt: Checkpointer,
        store: replay_disk.ChunkStore | None,
        env: envs.Env,
        evaluator: LocalEvaluator | EvalProcess | EvalProcesses,
        mesh: Mesh | None,
        hosts: Hosts,
    ):
        self.config, self.spec, self.ckpt, self.store = config, spec, ckpt, store
        self.env, self.evaluator, self.mesh, self.hosts = env, evaluator, mesh, hosts
        self.lanes = lanes.lanes(config)
        num_seeds, num_envs = len(self.lanes), config.envs_per_seed
        self.acfg = agent_config(config, spec.action_dim)
        self.programs = cached_programs(self.acfg, config, mesh)
        root = jax.random.key(config.seed)
        # Lanes of one seed (a sweep's settings) start from the same parameters.
        lane_seeds = jnp.array([lane.seed for lane in self.lanes])
        seed_keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(lane_seeds)
        agent = self._split(_init_seeds(self.acfg, seed_keys))
        # Made where it lives: the replay of all lanes may not fit on one device.
        buffer = jax.jit(
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
        key = self._everywhere(jax.random.fold_in(root, 1_000_003))
        self.eval_key = jax.random.fold_in(root, 2_000_003)  # the evaluations' own stream
        self.hold_keys = self._split(hold_keys(config))
        self.per_call = updates_per_call(config)  # updates a call of the learn program
        key, k_reset = jax.random.split(key)
        state, ts = env.reset(hosts.env_key(k_reset))
        ts = hosts.to_global(ts)
        returns = self._split(jnp.zeros((num_seeds, num_envs)))
        self.carry = Carry(
            hosts,
            agent=agent,
            buffer=buffer,
            key=key,
            state=state,
            ts=ts,
            returns=returns,
            seed_frames=config.replay.seed_frames,
            log_every=config.log_every_frames,
        )
        self._no_action = self._split(jnp.zeros((num_seeds, num_envs, spec.action_dim)))
        self.resumed_from = None  # the frame of the checkpoint this run resumed from
        self.evals = None  # while `run` runs: its Evaluations
        self.stop = None
        self.wait_env_s = 0.0  # the main thread's wait for the env's steps (host_seconds)
        if ckpt.latest_step() is None:
            if store is not None:
                store.forget_after(0)  # files of an earlier run whose checkpoints were deleted
            self._add(self.carry.ts, self._no_action)
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

    def host_seconds(self) -> dict[str, float]:
        """Host seconds since the last call: the env thread's stages (`env_action`,
        `env_physics`, `env_draw`, `env_post`: envs.Env.take_host_seconds) and the main
        thread's wait for the env's step (`wait_env`). Where `env_action` is large, the env
        waits for the accelerator; where the other three fill the iteration, the accelerator
        waits for the env (docs/design.md)."""
        taken = {f"env_{k}": s for k, s in self.env.take_host_seconds().items()}
        taken["wait_env"], self.wait_env_s = self.wait_env_s, 0.0
        return taken

    def eval_due(self) -> bool:
        """An evaluation is due at this frame and has not started."""
        return eval_due(self.carry, self.config.total_frames)

    # -- checkpoints -------------------------------------------------------------------------
    def save(self, wall_s: float) -> None:
        # The loop saves before starting an evaluation due at this frame (see `run`), so the
        # evaluations in flight or queued here started earlier: their rows and eval-env state
        # belong to this checkpoint.
        self.evals.finish(keep=0)
        c = self.carry
        c.counters["wall_s"] = wall_s
        if self.store is not None:
            self.store.save_partial(c.buffer, c.counters["rows"])
        extra = c.extra(
            env_rng=self.env.host_state(),
            eval_env_rng=self.evaluator.host_state(),
            replay_on_disk=self.store is not None,
        )
        self.ckpt.save(c.counters["frame"], c.tree(), extra=extra)
        if self.store is not None:
            rows = c.counters["rows"]
            kept = replay_rows_kept(self.ckpt, rows)
            if kept is not None:
                self.store.prune(rows, kept | {rows})

    def _restore(self) -> None:
        c = self.carry
        # orbax places arrays as the template's are: on several devices, the current split,
        # whatever the split of the run that saved them.
        step, restored, extra = self.ckpt.restore(c.tree())
        if self.mesh is None:
            restored = jax.tree.map(uncommitted, restored)
        c.load(restored, extra)
        self.env.set_host_state(extra["env_rng"])
        self.evaluator.set_host_state(extra["eval_env_rng"])
        c.load_host_values(extra, self.config.eval_every_frames)
        frame = c.counters["frame"]
        self.resumed_from = frame
        rows = c.counters["rows"]
        if self.store is not None and extra["replay_on_disk"]:
            self.store.forget_after(rows)
            t0 = time.perf_counter()
            if self.hosts.multi:  # each process reads its lanes' files into its block
                local = self.store.restore(self.hosts.to_local(c.buffer), rows)
                c.buffer = self.hosts.to_global(local).replace(**restored["replay"])
            else:
                buffer = self.store.restore(c.buffer, rows).replace(**restored["replay"])
                c.buffer = self._split(buffer)
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
            why = (
                "this run reads none: replay.disk=False"
                if extra["replay_on_disk"]
                else "the run that saved it kept none on disk: replay.disk=False"
            )
            log.warning(
                "resumed from checkpoint %d (frame %d per seed) without its replay (%s); "
                "collecting %d seed frames again before updating",
                step,
                frame,
                why,
                self.config.replay.seed_frames,
            )
            c.lv["seed_frames"] = frame + self.config.replay.seed_frames
            c.counters["rows"] = 0
            if self.store is not None:
                self.store.forget_after(0)
            # The env is mid-episode; the empty replay starts an episode at its current timestep.
            self._add(c.ts.replace(first=jnp.ones_like(c.ts.first)), self._no_action)

    # -- one step ----------------------------------------------------------------------------
    def _add(self, ts, action) -> None:
        c = self.carry
        c.buffer = self.programs.add(c.buffer, ts, action)
        c.counters["rows"] += 1
        if self.store is not None:
            self.store.added(c.buffer, c.counters["rows"])

    def step(self, progress: Progress) -> None:
        """One iteration: act, step the envs, update while they render, add to the replay."""
        config, programs, hosts, c = self.config, self.programs, self.hosts, self.carry
        counters, lv = c.counters, c.lv
        c.key, k_act, k_learn = jax.random.split(c.key, 3)
        # An env whose episode ended restarts this step: it shows a first frame, adds no
        # transition and owes no update. DMC envs all end together; kitchen envs end on success.
        stepping = ~np.asarray(c.state.last)  # [S, E]; several processes: [S / P, E], here
        # The step's decisions use sums over every process's envs (and any process's stop
        # request), so that all of them dispatch the same programs.
        request = getattr(self.stop, "request", None)
        steps, signum = hosts.agree([stepping.sum(), (request and request.signum) or 0]).T
        steps = int(steps.sum())
        if signum.any():
            self.stop.signum = int(signum.max())
        steps_per_seed = steps / len(self.lanes)
        if hosts.multi:
            stepping = hosts.place_local(stepping)
        action, c.agent = programs.act(c.agent, c.ts.obs, k_act, stepping, self.hold_keys)
        future = self.env.step_async(c.state, hosts.to_local(action))
        # Updates are dispatched while the env thread renders the next observations.
        if counters["frame"] >= lv["seed_frames"] and steps_per_seed:
            lv["steps_owed"] += steps_per_seed / config.agent.update_every_steps
            per_call = self.per_call
            n = int(lv["steps_owed"]) // per_call * per_call  # whole calls: the rest owed
            lv["steps_owed"] -= n
            if n and not counters["updates"]:  # once: the replay must hold a batch
                replay.check_can_sample(
                    replay.num_transitions(hosts.to_local(c.buffer), self.acfg.frame_stack),
                    config.agent.batch_size,
                )
            # While an evaluation runs in the background on the training's devices, its steps'
            # programs queue behind the updates dispatched before them: each call of updates is
            # dispatched only once the one before it has finished, so they wait for one call
            # (self.per_call updates), not for all. (An evaluation in a process of its
            # own queues nothing here.)
            short_queue = self.evals.beside_training
            keys = jax.random.split(k_learn, n) if n else ()
            for k in keys.reshape(n // per_call, per_call) if n and per_call > 1 else keys:
                if short_queue and c.metric_sum is not None:
                    jax.block_until_ready(c.metric_sum)
                c.agent, metrics = programs.learn(c.agent, c.buffer, k)
                c.metric_sum = (
                    metrics if c.metric_sum is None else programs.add_metrics(c.metric_sum, metrics)
                )
                lv["metric_count"] += per_call
            counters["updates"] += n
        t_wait = time.perf_counter()
        c.state, ts = future.result()
        self.wait_env_s += time.perf_counter() - t_wait
        c.ts = hosts.to_global(ts)
        self._add(c.ts, action)
        c.returns, ended_returns = programs.accumulate(c.returns, c.ts)
        counters["iteration"] += 1
        # Frames count per seed over its envs (the mean over seeds where their envs differ).
        lv["env_steps"] += steps
        frames = lv["env_steps"] // len(self.lanes) * self.spec.action_repeat - counters["frame"]
        if frames:
            counters["frame"] += frames
            progress.advance(frames)
        ended = np.asarray(c.state.last)
        # Read at the next log row: reading them now would wait for this step's updates before
        # the next action, every step an episode ends (the kitchen's, on success).
        c.add_ended(ended_returns, ended)
        ended_all = int(hosts.agree([ended.sum()]).sum())
        if ended_all:
            lv["episodes_ended"] += ended_all
            counters["episode"] = lv["episodes_ended"] // (ended.size * hosts.count)  # per env
            c.episodes_pending = True

    # -- the loop ----------------------------------------------------------------------------
    def run(self, logger: RunLogger, workdir: pathlib.Path, stop) -> None:
        """Train to config.total_frames, or until `stop` (a StopRequest, or signals.AgreedStop
        with several processes), then checkpoint and run the closing evaluation."""
        config, counters = self.config, self.carry.counters
        ckpt_every = config.checkpoint_every_frames
        every = lambda n: (counters["frame"] // n + 1) * n  # noqa: E731
        next_ckpt = every(ckpt_every) if ckpt_every else None
        progress = Progress(config.progress, config.total_frames, counters["frame"])
        self.evals = Evaluations(
            self.evaluator,
            self.carry,
            hosts=self.hosts,
            key=self.eval_key,
            background=config.eval_in_background and not self.hosts.multi,
            total_frames=config.total_frames,
            every_frames=config.eval_every_frames,
            videos=pathlib.Path(workdir).resolve() / "videos" if config.save_video else None,
            lane_names=[self.lanes[i].name for i in self.hosts.lanes],
            num_lanes=len(self.lanes),
            logger=logger,
            progress=progress,
        )
        self.stop = stop
        t_start, wall0 = time.perf_counter(), counters["wall_s"]
        train_log = TrainLog(
            logger,
            progress,
            self.hosts,
            len(self.lanes),
            config.log_every_frames,
            t_start,
            iteration=counters["iteration"],
            updates=counters["updates"],
            host_seconds=self.host_seconds,
        )
        self.host_seconds()  # the steps of the env's reset and of earlier runs are not counted
        wall = lambda: wall0 + time.perf_counter() - t_start  # noqa: E731
        trace = Trace(config.profile, pathlib.Path(workdir), counters["frame"])
        c = self.carry
        sync = lambda: jax.block_until_ready((c.agent, c.buffer, c.ts))  # noqa: E731
        try:
            before_training(stop, self.ckpt.latest_step())
            # An evaluation a stop cut short runs first (the resumed run continues from there).
            self.evals.start_if_due(wall(), stop)
            # A checkpoint at an evaluation's frame is saved before that evaluation starts
            # (it holds it as due; a resumed run redoes it, with the same parameters): saving
            # never waits for an evaluation of its own frame, ~20 s on a GPU.
            while counters["frame"] < config.total_frames and not stop:
                trace.tick(counters["frame"], sync)
                self.step(progress)
                train_log.write_if_due(c)
                if next_ckpt is not None and counters["frame"] >= next_ckpt:
                    self.save(wall())
                    next_ckpt = every(ckpt_every)
                if counters["frame"] < config.total_frames:
                    self.evals.start_if_due(wall(), stop)
            if stop:
                log.warning(
                    "%s: saving a checkpoint at frame %d per seed, then stopping",
                    stop.name,
                    counters["frame"],
                )
            trace.stop(sync)
            if self.ckpt.latest_step() != counters["frame"]:
                self.save(wall())
            self.evals.start_if_due(wall(), stop)  # the closing evaluation (none when stopped)
            self.evals.finish(keep=0)
            counters["wall_s"] = wall()
        finally:
            self.evals.close()
            progress.close()
            trace.stop()  # a failing run's trace, without waiting on its arrays
