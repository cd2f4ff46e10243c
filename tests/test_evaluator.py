"""Evaluations in a process of their own (dear_jax/evaluator.py) against those in this process."""

import concurrent.futures
import os
import pathlib
import signal
import subprocess
import sys
import time

import cv2
import jax
import numpy as np
import pytest

from dear_jax import experiment, lanes, update
from dear_jax.devices import Hosts
from dear_jax.evaluator import EvalProcess, LocalEvaluator
from dear_jax.programs import build_programs
from tests.test_run import ROOT, tiny_config


def _agent_params(config):
    acfg = experiment.agent_config(config, action_dim=6)  # walker
    keys = jax.random.split(jax.random.key(3), config.seeds)
    return update.init_seeds(acfg, keys).params, acfg


def _frames(path: pathlib.Path) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while (read := cap.read())[0]:
        frames.append(read[1])
    cap.release()
    return np.stack(frames)


def _local_evaluator(config, acfg) -> LocalEvaluator:
    """The evaluator of this process that an evaluation process's answers are held against."""
    hosts = Hosts(None, lanes.num_lanes(config))
    env = experiment.make_env(config, envs_per_seed=config.num_eval_episodes, split="val", seed=1)
    step = build_programs(acfg, experiment.hparams(config), config).evaluate_step
    return LocalEvaluator(env, step, hosts)


def test_the_eval_process_evaluates_as_this_process_does(tmp_path):
    """Same parameters, same key: the child's episodes, returns, cosines and the videos it writes
    are this process's (float32 on the CPU both), and so is the eval env's host state after them;
    restoring that state replays the same episodes there."""
    config = tiny_config()
    params, acfg = _agent_params(config)
    local = _local_evaluator(config, acfg)
    key = jax.random.key(7)
    with EvalProcess(config) as remote:
        try:
            start = remote.host_state()
            local.set_host_state(start)
            videos = {w: [tmp_path / w / "s0.mp4", None] for w in ("child", "here")}
            got = remote.evaluate(params, key, videos=videos["child"])
            want = local.evaluate(params, key, videos=videos["here"])
            assert set(got) == set(want) == {"episode_return", "cos_agent_env", "abs_cos_agent_env"}
            for name in want:
                np.testing.assert_array_equal(got[name], want[name], err_msg=name)
            # seed 1's path is None: not written
            assert [p.name for p in (tmp_path / "child").iterdir()] == ["s0.mp4"]
            child, here = _frames(videos["child"][0]), _frames(videos["here"][0])
            assert len(child) == config.env.episode_frames // config.env.action_repeat + 1
            np.testing.assert_array_equal(child, here)
            assert repr(remote.host_state()) == repr(local.host_state()) != repr(start)
            remote.set_host_state(start)  # as a resumed run, or one whose evaluation was cut
            again = remote.evaluate(params, key)
            np.testing.assert_array_equal(again["episode_return"], got["episode_return"])
        finally:
            local.close()


def test_on_the_accelerator_the_eval_process_runs_the_trainings_own_program():
    """policy_on="accelerator" (the resolved eval_device): the child evaluates with the
    training's program (bf16 here, on this machine's only device, the CPU), so its returns are
    this process's with that program, and differ from the float32 host program's that "cpu"
    runs. With eval_nice it runs at a lower priority than this process."""
    config = tiny_config(**{"agent.compute_dtype": "bfloat16", "eval_nice": 3})
    params, acfg = _agent_params(config)
    hosts = Hosts(None, lanes.num_lanes(config))
    programs = build_programs(acfg, experiment.hparams(config), config)
    key = jax.random.key(7)
    want = {}
    with EvalProcess(config, policy_on="accelerator") as remote:
        start = remote.host_state()
        got = remote.evaluate(params, key)
        # eval_nice: the child runs 3 nicer than this process
        niceness = os.getpriority(os.PRIO_PROCESS, remote._proc.pid)
        assert niceness == min(os.getpriority(os.PRIO_PROCESS, 0) + 3, 19)
    env = experiment.make_env(config, envs_per_seed=config.num_eval_episodes, split="val", seed=1)
    try:
        for name, step in (("bf16", programs.evaluate_step), ("f32", programs.evaluate_step_host)):
            local = LocalEvaluator(env, step, hosts)
            local.set_host_state(start)
            want[name] = local.evaluate(params, key)
    finally:
        env.close()
    for name in want["bf16"]:
        np.testing.assert_array_equal(got[name], want["bf16"][name], err_msg=name)
    assert not np.array_equal(got["abs_cos_agent_env"], want["f32"]["abs_cos_agent_env"])


def test_the_eval_process_takes_a_device_the_training_leaves_idle():
    """A run started with more GPUs than it trains on evaluates on the first idle one; with
    none idle, on the first (beside the training)."""
    from dear_jax.evaluator import spare_device

    gpus = ["gpu0", "gpu1", "gpu2"]
    assert spare_device(gpus, 1) == "gpu1"
    assert spare_device(gpus, 2) == "gpu2"
    assert spare_device(gpus, 3) == spare_device(gpus, "all") == "gpu0"
    assert spare_device(gpus[:1], 1) == "gpu0"


def test_a_failure_in_the_eval_process_is_raised_here_with_its_traceback(tmp_path):
    config = tiny_config(**{"env.distraction": "easy", "env.background_dir": str(tmp_path)})
    with EvalProcess(config) as remote, pytest.raises(RuntimeError) as failure:
        remote.host_state()
    assert "the evaluation process failed" in str(failure.value)
    assert "Traceback" in str(failure.value) and str(tmp_path) in str(failure.value)


def test_an_eval_process_that_died_is_named_as_dead():
    """Killed (by the OOM killer, say), the evaluation process's next request says it died and
    with which exit code, not a bare broken pipe."""
    with EvalProcess(tiny_config()) as remote:
        state = remote.host_state()
        os.kill(remote._proc.pid, signal.SIGKILL)
        remote._proc.join(timeout=30)
        with pytest.raises(RuntimeError, match=r"the evaluation process died \(exit code -9\)"):
            remote.set_host_state(state)


def _running(pid: int) -> bool:
    """The process exists and has not exited (an exited child nobody has reaped yet is a zombie,
    state Z, whoever its new parent is)."""
    try:
        stat = pathlib.Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_the_eval_process_ends_with_the_training_process_even_when_killed():
    """SIGKILL gives the training process no chance to close it: the child sees its pipe close
    and exits (with its render workers), leaving no process behind. SIGINT (a Ctrl-C to the
    terminal's process group) does not stop it: the training process decides."""
    code = (
        "import os, sys; from tests.test_run import tiny_config; "
        "from dear_jax.evaluator import EvalProcess; e = EvalProcess(tiny_config()); "
        "e.host_state(); print(e._proc.pid, flush=True); sys.stdin.read()"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", code], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        child = int(parent.stdout.readline())
        os.kill(child, signal.SIGINT)
        time.sleep(1.0)
        assert _running(child)
        parent.kill()
        parent.wait()
        for _ in range(60):
            if not _running(child):
                break
            time.sleep(0.5)
        else:
            os.kill(child, signal.SIGKILL)
            pytest.fail("the evaluation process outlived the killed training process")
    finally:
        parent.kill()


def test_a_stuck_eval_process_is_killed_and_named_as_stuck():
    """Alive but stuck (stopped here by SIGSTOP), the evaluation process says nothing: after its
    `silence_s` the call kills it and says so, instead of waiting for ever."""
    with EvalProcess(tiny_config(), silence_s=2.0) as remote:
        state = remote.host_state()
        os.kill(remote._proc.pid, signal.SIGSTOP)
        pool = concurrent.futures.ThreadPoolExecutor(1)
        call = pool.submit(remote.set_host_state, state)
        try:  # a call that never returns fails here (TimeoutError) rather than hanging the suite
            with pytest.raises(RuntimeError, match=r"said nothing for 2 s: stuck \(an env step"):
                call.result(timeout=60)
            assert not remote._proc.is_alive()
        finally:
            if remote._proc.is_alive():
                os.kill(remote._proc.pid, signal.SIGKILL)  # so that the call ends
            pool.shutdown()


def test_an_eval_process_that_works_longer_than_its_silence_is_not_stuck():
    """An evaluation that outlasts `silence_s` ends with its answer, the one this process
    computes: the child says it is alive while it steps."""
    config = tiny_config()
    params, acfg = _agent_params(config)
    local = _local_evaluator(config, acfg)
    with EvalProcess(config, silence_s=0.25) as remote:
        try:
            remote.silence_s = 600.0  # its first evaluation compiles the policy's step, silently
            remote.evaluate(params, jax.random.key(6))
            remote.silence_s = 0.25
            local.set_host_state(remote.host_state())
            t0 = time.monotonic()
            got = remote.evaluate(params, jax.random.key(7))
            took = time.monotonic() - t0
            want = local.evaluate(params, jax.random.key(7))
        finally:
            local.close()
    assert took > 2 * remote.silence_s  # else this shows nothing
    np.testing.assert_array_equal(got["episode_return"], want["episode_return"])
