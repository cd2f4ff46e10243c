"""Evaluation episodes: in the training process, or in a process of their own (its policy on
the host's CPU or on the accelerator).

The loop evaluates through one of two evaluators with the same methods (`config.eval_device`):
- `LocalEvaluator`: the eval env and the training's `Programs.evaluate_step`, in this process;
- `EvalProcess` ("cpu" or "accelerator"; "auto" in one process picks one of them, by
  whether there is a GPU): a child process with its own Python
  interpreter, XLA:CPU and render workers runs the eval env and the float32 policy
  (`Programs.evaluate_step_host`). The training process only sends the policy's parameters and
  receives the metrics: an evaluation takes neither its Python thread, which dispatches the
  updates, nor the accelerator's queue. It still shares the CPU cores and, through its render
  workers' EGL contexts, the GPU. With "accelerator" the child runs the training's own policy
  program (`Programs.evaluate_step`, the training's dtype) on the accelerator, in a context of
  its own that allocates only what it uses; its CPU threads are then nearly idle.

Measured on an H100 (benchmarks/RESULTS.md, "Evaluation"): evaluating at
twice the paper's rate, the DrQ-v2 learning check's loop trained at 786 frames/s with
"accelerator" and 703 with "cpu" (1,135 without evaluating). At the paper's rate, a 500k-frame
DrQ-v2 run took 1.22x the time of its training alone ("A whole run against its training alone";
its "auto" evaluations ran the policy on the host's CPU: until 2026-11-29 the resolved
eval_device did not reach the evaluation process).

With training at ~1,585 frames/s, a 500k-frame DrQ-v2 run's evaluations (21.5 s each) outlasted
the training between two of them, and the run took 1.27x the time of its training alone
(benchmarks/RESULTS.md). The process therefore steps its env's CPU physics on up to 8 threads and
keeps the env's arrays on XLA:CPU (`build`, env_on="cpu"): beside a training run on an H100, an
evaluation step of that check took 24.5 ms instead of 34.7 (benchmarks/evaluation.py), and the
loop lets evaluations queue (`evaluations.MAX_PENDING_EVALS`).

Both evaluate one episode in each of the eval env's E envs per seed (`evaluate`), write its videos
where they run (the evaluation's thread or process, never the training loop's: assembling and
encoding three 500-frame videos takes seconds of CPU), and keep the eval env's host state
(episode-start RNG, distractions) for checkpoints: an evaluation run in either continues the same
sequence of episodes.
"""

from __future__ import annotations

import os
import pickle
import threading
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np

from dear_jax.video import side_by_side, write_video
from envs import forkserver

POLICY_PLACES = ("cpu", "accelerator")  # where an evaluation process runs its policy
# The parameters an evaluation reads (the critic's and the TED classifier's are not sent).
POLICY_PARAMS = ("encoder", "actor", "mask_decoder")
# The longest the child may take to import and build its env and render workers, and by default
# to answer a request: it says it is alive a hundred times in that span while it evaluates, so
# silent for longer it is stuck (a render worker or an env step that never returns) and is
# killed, which fails the run instead of hanging it.
_SILENCE_S = 600.0


class EvalAborted(Exception):
    """An evaluation was cut short by a stop request; the run evaluates again after resuming."""


def evaluate(env, step, params, key, *, video: bool, stop=lambda: False, hosts=None):
    """One episode in each of the eval env's E envs per seed, deterministic actions of the
    policy with `params` (the agent's, [S]-stacked); `step` is `Programs.evaluate_step` or, with
    params and env on the host's CPU, `Programs.evaluate_step_host`.

    Returns per-seed metrics ([S] arrays) and, if asked, video frames of env 0 per seed.
    Raises EvalAborted when `stop()` turns true (checked every step). With several processes
    (`hosts`, dear_jax.devices.Hosts), those of this process's lanes, whose envs `env` steps; the
    episodes end when every process's have.
    """
    to_global = hosts.to_global if hosts else lambda x: x
    to_local = hosts.to_local if hosts else lambda x: x
    agree = hosts.agree if hosts else lambda values: np.asarray(values)[None]
    state, ts = env.reset(key)
    returns = jnp.zeros(env.shape)
    success = jnp.zeros(env.shape)
    done = np.zeros(env.shape, bool)  # envs whose first episode has ended (kitchen: at success)
    # The latent cosines of every observation of each env's first episode: sums and counts.
    cos_sum, abs_cos_sum, counted = (np.zeros(env.shape) for _ in range(3))
    frames = []
    while True:
        action, cos, pred = to_local(step(params, to_global(ts.obs)))
        if video:
            frames.append((ts.frame[:, 0], ts.true_mask[:, 0], pred))
        cos, live = np.asarray(cos), ~done  # live: this observation is of the first episode
        cos_sum += np.where(live, cos, 0.0)
        abs_cos_sum += np.where(live, np.abs(cos), 0.0)
        counted += live
        done |= np.asarray(state.last)
        if agree([done.all()]).all():
            break
        if stop():
            raise EvalAborted
        live = jnp.asarray(~done)  # an ended env restarts; its next episode does not count
        state, ts = env.step(state, action)
        returns = returns + jnp.where(live, ts.reward, 0.0)
        success = jnp.maximum(success, jnp.where(live, ts.success, 0.0))
    metrics = {
        "episode_return": np.asarray(returns.mean(1)),
        "cos_agent_env": cos_sum.sum(1) / counted.sum(1),
        "abs_cos_agent_env": abs_cos_sum.sum(1) / counted.sum(1),
    }
    if env.spec.has_success:
        metrics["success"] = np.asarray(success.mean(1))
    clips = {}
    if video:
        rgb, true_mask, pred = (np.asarray(jnp.stack(x, 1)) for x in zip(*frames))
        clips = {s: side_by_side(rgb[s], true_mask[s], pred[s]) for s in range(rgb.shape[0])}
    return metrics, clips


def eval_states(state: dict) -> list[dict]:
    """The eval envs' host states in a checkpoint's `eval_env_rng`: one per evaluation process
    (`EvalProcesses`), or the one of a single evaluator."""
    return list(state["processes"]) if "processes" in state else [state]


def write_videos(clips: dict, paths) -> None:
    """Each seed's clip (`evaluate`'s) to its path, paths[seed] (a .mp4 path or None: not written)."""
    for s, clip in clips.items():
        if paths[s] is not None:
            write_video(paths[s], clip, fps=30)


class LocalEvaluator:
    """Evaluations in this process: `env` (on the training's devices) and the training's
    `Programs.evaluate_step`."""

    slots = 1  # evaluations at once

    def __init__(self, env, step, hosts=None):
        self.env, self.step, self.hosts = env, step, hosts

    def evaluator_for(self, index: int) -> LocalEvaluator:
        """The evaluator of a run's index-th evaluation: this one."""
        return self

    def host_state(self) -> dict:
        return self.env.host_state()

    def set_host_state(self, state: dict) -> None:
        self.env.set_host_state(eval_states(state)[0])

    def evaluate(self, params, key, *, videos=None, stop=lambda: False) -> dict:
        """Per-seed metrics; with `videos` (a path or None per seed), writes those videos."""
        metrics, clips = evaluate(
            self.env, self.step, params, key, video=videos is not None, stop=stop, hosts=self.hosts
        )
        write_videos(clips, videos)
        return metrics

    def close(self) -> None:
        self.env.close()


class EvalProcess:
    """Evaluations in a child process (one process runs one at a time), its policy on the host's
    CPU in float32 (`policy_on` "cpu") or on the accelerator ("accelerator": the training's
    policy program, its dtype): the run's resolved eval_device (`experiment.eval_device`).

    The child builds the config's eval env and the policy, then serves requests until
    this side closes the pipe (or exits, even by SIGKILL). It ignores the stop signals: the
    training process handles those, and lets the evaluations in flight or queued end before it
    checkpoints.
    An evaluation here always runs to its end (`stop` is not read). Between its env steps the
    child says it is alive, a hundred times in `silence_s`; one silent for longer (its first
    evaluation's compiles and its video writing are silent too) is stuck: it is killed and the
    call raises. Calls from several threads take turns. `stream`: which of the run's evaluation
    processes this is (`EvalProcesses`): its eval env's seed."""

    slots = 1

    def __init__(
        self, config, stream: int = 0, policy_on: str = "cpu", silence_s: float = _SILENCE_S
    ):
        if policy_on not in POLICY_PLACES:
            raise ValueError(f"policy_on={policy_on!r}: valid: {', '.join(POLICY_PLACES)}")
        # Never fork a process that holds CUDA: the process's fork server (as the render
        # workers', envs/render_pool.py) holds none and forks it with jax and the envs imported.
        ctx = forkserver.context("dear_jax.evaluator")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_serve,
            args=(child, pickle.dumps(config), stream, policy_on, silence_s / 100),
            name=f"eval{stream}",
        )
        self._proc.start()
        child.close()
        self.stream = stream
        self._state = None  # the eval env's host state, as of the last answer
        self._lock = threading.Lock()  # one request and its answer at a time
        self.silence_s = silence_s

    def evaluator_for(self, index: int) -> EvalProcess:
        return self

    def _call(self, *request):
        with self._lock:
            return self._exchange(request, self.silence_s)

    def _exchange(self, request: tuple, silence_s: float):
        try:
            if request:
                self._conn.send(request)
            status = "alive"
            while status == "alive":  # the child's beats while it works
                heard = time.monotonic()
                while not self._conn.poll(min(1.0, silence_s / 4)):
                    if not self._proc.is_alive():
                        raise EOFError
                    if time.monotonic() - heard > silence_s:
                        self._proc.kill()
                        self._proc.join(timeout=30)
                        doing = (
                            "an env step or render worker that never returned"
                            if request
                            else "importing, or building its env and render workers"
                        )
                        raise RuntimeError(
                            f"the evaluation process said nothing for {silence_s:g} s: stuck "
                            f"({doing}); killed"
                        )
                status, payload, state = self._conn.recv()
        except (EOFError, ConnectionError) as e:  # its end of the pipe closed: it has died
            self._proc.join(timeout=5)
            raise RuntimeError(
                f"the evaluation process died (exit code {self._proc.exitcode})"
            ) from e
        if status != "ok":
            raise RuntimeError(f"the evaluation process failed:\n{payload}")
        self._state = state
        return payload

    def _ready(self) -> None:
        with self._lock:
            if self._state is None:  # its first answer: built, with the env's initial host state
                self._exchange((), _SILENCE_S)

    def host_state(self) -> dict:
        self._ready()
        return self._state

    def set_host_state(self, state: dict) -> None:
        self._ready()
        self._call("set_host_state", eval_states(state)[0])

    def evaluate(self, params, key, *, videos=None, stop=lambda: False) -> dict:
        """As LocalEvaluator.evaluate; the child writes the videos."""
        self._ready()
        policy = {k: params[k] for k in POLICY_PARAMS if k in params}
        policy = jax.tree.map(np.asarray, policy)  # waits here for the parameters, not the loop
        key_data = np.asarray(jax.random.key_data(key))
        videos = None if videos is None else [None if p is None else str(p) for p in videos]
        return self._call("evaluate", policy, key_data, str(jax.random.key_impl(key)), videos)

    def close(self) -> None:
        if self._proc.is_alive():
            try:
                self._conn.send(("close",))
            except (BrokenPipeError, OSError):
                pass
            self._proc.join(timeout=30)
        if self._proc.is_alive():
            self._proc.kill()  # it ignores SIGTERM
            self._proc.join()
        self._conn.close()

    def __enter__(self) -> EvalProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class EvalProcesses:
    """`count` evaluation processes side by side: evaluation slot `index` (the
    loop's: frame // eval_every_frames, dear_jax/evaluations.py) runs in process index mod N
    (`evaluator_for`), so that the next evaluation can start while one still runs. Process i
    draws its episodes from its own stream (`experiment.make_eval_env`); the host state a
    checkpoint keeps is every process's, and one saved by fewer processes (or a single
    evaluator) restores theirs, the others starting their streams afresh."""

    def __init__(self, config, count: int, policy_on: str = "cpu"):
        self.processes = []
        try:
            for i in range(count):
                self.processes.append(EvalProcess(config, stream=i, policy_on=policy_on))
        except BaseException:
            self.close()
            raise
        self.slots = len(self.processes)

    def evaluator_for(self, index: int) -> EvalProcess:
        return self.processes[index % self.slots]

    def host_state(self) -> dict:
        return {"processes": [p.host_state() for p in self.processes]}

    def set_host_state(self, state: dict) -> None:
        for process, saved in zip(self.processes, eval_states(state)):
            process.set_host_state(saved)

    def close(self) -> None:
        for process in self.processes:
            process.close()

    def __enter__(self) -> EvalProcesses:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve(conn, config_bytes: bytes, stream: int, policy_on: str, beat_s: float) -> None:
    """The child: build the eval env and the policy (on the host's CPU, or on the accelerator),
    then answer requests, saying it is alive every `beat_s` while it evaluates."""
    forkserver.ignore_stop_signals()
    config = pickle.loads(config_bytes)
    on_accelerator = policy_on == "accelerator"
    if on_accelerator:  # beside the training's preallocated pool: only what it uses
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    else:
        jax.config.update("jax_platforms", "cpu")  # the accelerator stays the training's
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) >= 4:  # its thread pools (XLA:CPU, render workers) on half the cores
        os.sched_setaffinity(0, cores[len(cores) // 2 :])
    if config.get("eval_nice"):  # lower priority, for it and the processes it starts
        os.nice(config.eval_nice)

    last_beat = time.monotonic()

    def beat() -> bool:  # as `evaluate`'s stop, read every step: never stops it
        nonlocal last_beat
        if time.monotonic() - last_beat > beat_s:
            conn.send(("alive", None, None))
            last_beat = time.monotonic()
        return False

    env = None
    try:
        env, step, place = build(
            config,
            policy_on=policy_on,
            env_on="cpu" if config.env.eval_backend == "cpu" else "default",
            stream=stream,
        )
        conn.send(("ok", None, env.host_state()))
        while True:
            try:
                request = conn.recv()
            except EOFError:  # the training process has gone
                break
            if request[0] == "close":
                break
            try:
                if request[0] == "set_host_state":
                    env.set_host_state(request[1])
                    answer = None
                else:  # evaluate
                    policy, key_data, impl, videos = request[1:]
                    key = jax.random.wrap_key_data(jnp.asarray(key_data), impl=impl)
                    answer, clips = evaluate(
                        env, step, place(policy), key, video=videos is not None, stop=beat
                    )
                    write_videos(clips, videos)
                conn.send(("ok", answer, env.host_state()))
            except Exception:
                conn.send(("error", traceback.format_exc(), None))
    except Exception:
        conn.send(("error", traceback.format_exc(), None))
    finally:
        if env is not None:
            env.close()
        conn.close()


def spare_device(devices: list, training) -> jax.Device:
    """Where the evaluation process runs its policy on the accelerator: the first of `devices`
    (this host's) that the training (`config.devices` of them, from the first) leaves idle, so
    that a run given one GPU more than it trains on evaluates there; else the first."""
    used = len(devices) if training == "all" else training
    return devices[used] if used < len(devices) else devices[0]


def build(config, *, policy_on: str, env_on: str = "default", stream: int = 0):
    """The evaluation process's env and policy: (env, step, place), `place` putting the policy's
    parameters where `step` runs them.

    policy_on "accelerator": the training's own policy program (its dtype) on the accelerator
    (`spare_device`: one the training does not use, if there is one);
    "cpu": the float32 policy on XLA:CPU. env_on: where the env's array work (uploads, frame
    stack, compositing) runs, the process's default device ("default") or XLA:CPU ("cpu", which
    sets the process's default device, with CPU physics only; the evaluation process's choice
    with CPU physics). The env is `experiment.make_eval_env`'s (of evaluation process `stream`):
    CPU physics on env.eval_physics_threads threads. On an H100 beside a training run, ms per
    evaluation step of the DrQ-v2 learning check (benchmarks/evaluation.py --load): policy on the
    accelerator with the env "default" 34.7 (1 physics thread) / 30.9 (8), "cpu" 28.9 / 24.5;
    policy and env on XLA:CPU 42.0 / 36.4.
    """
    # The child imports these after setting its platform.
    from dear_jax import lanes
    from dear_jax.devices import Hosts
    from dear_jax.experiment import agent_config, hparams, make_eval_env
    from dear_jax.programs import build_programs

    if policy_on not in ("accelerator", "cpu") or env_on not in ("default", "cpu"):
        raise ValueError(
            f"policy_on={policy_on!r}, env_on={env_on!r}: policy_on is 'accelerator' or 'cpu', "
            "env_on 'default' or 'cpu'"
        )
    if env_on == "cpu":
        if config.env.eval_backend != "cpu":
            raise ValueError("env_on='cpu' needs CPU physics in the eval env (env.eval_backend)")
        # Every thread's default device, the env thread's too: the caller's process is changed.
        jax.config.update("jax_default_device", jax.devices("cpu")[0])
    if policy_on == "accelerator":
        policy_device = spare_device(jax.local_devices(), config.devices)
        if env_on == "default":  # the env's array work beside the policy
            jax.config.update("jax_default_device", policy_device)
    else:
        policy_device = jax.devices("cpu")[0]
    hosts = Hosts(None, lanes.num_lanes(config))
    env = make_eval_env(config, hosts=hosts, stream=stream, device=policy_device)
    acfg = agent_config(config, env.spec.action_dim)
    programs = build_programs(acfg, hparams(config), config)
    step = programs.evaluate_step if policy_on == "accelerator" else programs.evaluate_step_host
    return env, step, lambda policy: jax.device_put(policy, policy_device)
