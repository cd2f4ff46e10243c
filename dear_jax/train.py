"""`train(config, workdir)`: run (or resume) a whole experiment and return its summary.

S lanes (seeds, or settings x seeds: `dear_jax/lanes.py`) train as a vmapped axis, E
environments per lane, in one process (`dear_jax/loop.py`: the loop; docs/design.md: its data
flow). A resume continues exactly where the checkpoint left off (`dear_jax/carry.py` says what a
checkpoint holds; the replay comes back from its chunk files, `dear_jax/replay_disk.py`), and is
refused if a config field that changes learning differs (all but
`experiment.RESUMABLE_CHANGES`). One run per workdir (`run.lock`); SIGTERM / SIGINT checkpoint
and stop (`dear_jax/signals.py`).

Several devices (`config.devices`) split the lanes over a mesh, several processes
(`jax.distributed`, README "Several hosts") each their block of lanes (`dear_jax/devices.py`);
each seed gets the key it gets on one device, so its run is the same bit for bit.
"""

from __future__ import annotations

import contextlib
import json
import logging
import pathlib
import sys

from ml_collections import ConfigDict

from dear_jax import lanes, replay
from dear_jax.checkpoint import Checkpointer, IncompatibleCheckpointError
from dear_jax.devices import Hosts, batch_split, seed_groups, seed_mesh
from dear_jax.evaluator import EvalProcess, EvalProcesses, LocalEvaluator
from dear_jax.experiment import (
    ADDED_FIELDS,
    OWN_PROCESS,
    ConfigError,
    agent_config,
    eval_device,
    eval_processes,
    fingerprint,
    make_env,
    make_eval_env,
    replay_store,
    validate,
)
from dear_jax.lock import WorkdirLock
from dear_jax.logger import RunLogger, write_text_atomic
from dear_jax.loop import Loop
from dear_jax.programs import cached_programs
from dear_jax.signals import AgreedStop, Stopped, StopRequest, before_training
from dear_jax.summary import runs_per_gpu, write_summary

log = logging.getLogger("dear_jax")


def train(config: ConfigDict, workdir: str | pathlib.Path) -> dict:
    """Run (or resume) the experiment described by `config` in `workdir`; returns the summary.

    SIGTERM or SIGINT: the run checkpoints at the end of its step, writes its summary so far
    (`"stopped"`: the signal's name) and raises signals.Stopped.
    """
    # Held until the summary and curves are written: a signal then too asks for a stop (a
    # second one stops at once), and is not taken for one before training.
    with StopRequest() as stop:
        return _train(config, workdir, stop)


def _train(config: ConfigDict, workdir: str | pathlib.Path, stop: StopRequest) -> dict:
    validate(config)
    sharing = runs_per_gpu()  # read first: a bad value fails before any work
    mesh = seed_mesh(config.devices, lanes.num_lanes(config), config.devices_per_seed)
    hosts = Hosts(mesh, lanes.num_lanes(config))
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        stack.enter_context(WorkdirLock(workdir, hosts.index))
        stack.enter_context(switch_interval(config.env.switch_interval_ms))
        open_checkpoints = lambda: _checkpointer(config, workdir, stack)  # noqa: E731
        ckpt = None

        def starting():  # a stop while the run starts: nothing is trained, so nothing is saved
            if not hosts.multi:  # (with several processes, they stop together in the loop)
                before_training(stop, ckpt.latest_step() if ckpt else None)

        if (workdir / "checkpoints").is_dir():  # a changed config is refused before anything
            ckpt = open_checkpoints()
            _check_resumable(ckpt, hosts)
            finished = _finished(config, workdir, ckpt)
            if finished is not None:
                log.info(
                    "%s trained to %s frames per seed and ran its closing evaluation: nothing "
                    "to do (raise total_frames to train on)",
                    workdir,
                    f"{finished['frames_per_seed']:,}",
                )
                if not hosts.index and (workdir / "summary.md").is_file():
                    print((workdir / "summary.md").read_text())
                return finished
        env = stack.enter_context(
            make_env(
                config,
                envs_per_seed=config.envs_per_seed,
                split="train",
                seed=config.seed,
                mesh=mesh,
                hosts=hosts,
            )
        )
        starting()
        spec = env.spec
        _check_fits(config, spec, mesh)
        ckpt = ckpt or open_checkpoints()  # a new run's folder: only once the config works
        store = replay_store(config, spec, workdir, hosts)
        if store is not None:
            stack.callback(store.close)
        where = eval_device(config, hosts)
        processes = eval_processes(config, where)
        log.info(
            "evaluations: eval_device=%r (config: %r), %d process(es) (config: %d)",
            where,
            config.eval_device,
            processes,
            config.eval_processes,
        )
        evaluator = _evaluator(config, where, processes, spec, mesh, hosts)
        stack.callback(evaluator.close)
        starting()
        _log_split(mesh, hosts, lanes.num_lanes(config))
        loop = Loop(config, spec, ckpt, store, env, evaluator, mesh, hosts)
        starting()
        logger = _logger(config, workdir, hosts, loop)
        stack.callback(logger.close)
        if hosts.multi:  # true once any process got a signal, on every process at the same step
            stop = AgreedStop(stop)
        loop.run(logger, workdir, stop)
    if hosts.multi:  # every process's logs are written before process 0 sums them up
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("dear_jax: logs written")
    # A stopped run's summary is of what it has done so far (the report reads it); the resumed
    # run rewrites it.
    summary = {}
    if not hosts.index:
        try:
            summary = write_summary(
                workdir,
                config,
                spec,
                loop.carry.counters,
                devices=1 if mesh is None else mesh.size,
                stopped=stop.name if stop else None,
                evaluated_on=where,
                eval_processes=processes,
                runs_per_gpu=sharing,
            )
        except Exception as e:  # a stopped run still exits as stopped (and resumable)
            if not stop:
                raise
            log.warning("the stopped run's summary was not written: %s", e)
        _draw_curves(workdir)
    if stop:
        raise Stopped(
            f"stopped by {stop.name} at frame {loop.carry.counters['frame']:,} per seed; "
            f"checkpoint saved in {workdir / 'checkpoints'}; rerun the same command to resume",
            stop.signum,
        )
    return summary


def _draw_curves(workdir: pathlib.Path) -> None:
    """The run's learning curves so far, <workdir>/curves.png (`python -m dear_jax.report
    curves` draws several runs'); one that cannot be drawn is a warning, not the run's failure."""
    from dear_jax import plot

    try:
        log.info("learning curves: %s", plot.plot([workdir], workdir / "curves.png"))
    except Exception as e:
        log.warning("curves.png was not drawn: %s", e)


@contextlib.contextmanager
def switch_interval(ms: float):
    """Python's thread switch interval set to `ms` (0: left as it is) inside, restored after."""
    before = sys.getswitchinterval()
    if ms:
        sys.setswitchinterval(ms / 1e3)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def _checkpointer(config, workdir: pathlib.Path, stack: contextlib.ExitStack) -> Checkpointer:
    ckpt = Checkpointer(
        workdir / "checkpoints",
        fingerprint=fingerprint(config),
        added_fields=ADDED_FIELDS,
        keep=config.keep_checkpoints,
    )
    stack.callback(ckpt.close)
    return ckpt


def _finished(config: ConfigDict, workdir: pathlib.Path, ckpt: Checkpointer) -> dict | None:
    """The summary of the run in `workdir` if it has trained to config.total_frames and run its
    closing evaluation (a rerun would only redo that evaluation), else None. A run's summary says
    it finished (not "stopped") only once its closing evaluation has ended."""
    latest = ckpt.latest_step()
    path = workdir / "summary.json"
    if latest is None or latest < config.total_frames or not path.is_file():
        return None
    summary = json.loads(path.read_text())
    done = summary.get("stopped") is None and summary.get("frames_per_seed", 0) >= latest
    return summary if done else None


def _check_resumable(ckpt: Checkpointer, hosts: Hosts) -> None:
    """Refuse to resume from a latest checkpoint of another config (fields that change what a
    run learns) or of another number of processes."""
    if ckpt.latest_step() is None:
        return
    step, saved, extra = ckpt.read_meta()
    ckpt.check_fingerprint(saved, step)
    if extra.get("processes", 1) != hosts.count:
        raise IncompatibleCheckpointError(
            f"checkpoint {step} in {ckpt.directory} was written by "
            f"{extra.get('processes', 1)} process(es), and this run has "
            f"{hosts.count}; resume with as many processes (each holds the host state "
            "of its lanes' envs), or start in a new --workdir"
        )


def _check_fits(config: ConfigDict, spec, mesh) -> None:
    """Refuse an n-step return longer than an episode, or a replay too large for a device."""
    if config.agent.nstep > spec.episode_steps:
        raise ConfigError(
            f"agent.nstep={config.agent.nstep} is longer than an episode of {spec.name} "
            f"({spec.episode_steps} agent steps); lower agent.nstep"
        )
    n, groups = lanes.num_lanes(config), seed_groups(mesh)
    sweep = n > config.seeds
    what = f"lanes ({config.seeds} seeds x {n // config.seeds} settings)" if sweep else "seeds"
    if groups > 1:
        what += f" per device ({n} over {groups} devices)"
    replay.check_fits(
        n // groups, config.replay.capacity, spec.frame_shape, spec.action_dim, lanes=what
    )


def _evaluator(config: ConfigDict, where: str, processes: int, spec, mesh, hosts: Hosts):
    """The evaluator `where` (the resolved eval_device) says: `processes` processes of their
    own, started now (they build while this process compiles), or the eval env here."""
    if where in OWN_PROCESS:
        if processes == 1:
            return EvalProcess(config, policy_on=where)
        return EvalProcesses(config, processes, policy_on=where)
    eval_env = make_eval_env(config, mesh=mesh, hosts=hosts)
    acfg = agent_config(config, spec.action_dim)
    return LocalEvaluator(eval_env, cached_programs(acfg, config, mesh).evaluate_step, hosts)


def _log_split(mesh, hosts: Hosts, num_lanes: int) -> None:
    if mesh is None:
        return
    log.info(
        "%d lanes split over %d devices (%d each, each lane's batch over %d) of %d process(es): "
        "%s; here lanes %d to %d",
        num_lanes,
        mesh.size,
        num_lanes // seed_groups(mesh),
        batch_split(mesh),
        hosts.count,
        ", ".join(str(d) for d in mesh.devices),
        hosts.lanes[0],
        hosts.lanes[-1],
    )


def _logger(config: ConfigDict, workdir: pathlib.Path, hosts: Hosts, loop: Loop) -> RunLogger:
    """The logs of this process's lanes; the run's config beside them (and each lane's own
    settings beside its logs)."""
    if hosts.index == 0:
        write_text_atomic(workdir / "config.json", config.to_json(indent=1))
    runs = lanes.lanes(config)
    mine = [runs[i] for i in hosts.lanes]  # the lanes whose envs, logs and files are here
    # An evaluation due at the checkpoint's frame runs again (and logs its row again).
    redo = ("eval",) if loop.resumed_from is not None and loop.eval_due() else ()
    logger = RunLogger(
        workdir,
        len(mine),
        names=[lane.name for lane in mine],
        resume_frame=loop.resumed_from,
        redo=redo,
    )
    if len(runs) > 1 or runs[0].settings:
        for i, lane in enumerate(mine):
            text = lanes.lane_config(config, lane).to_json(indent=1)
            write_text_atomic(logger.seed_dir(i) / "config.json", text)
    return logger
