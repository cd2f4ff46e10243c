"""Several processes (`jax.distributed`), each stepping the envs of its block of lanes: a run
completes without any process waiting on another, writes every lane's files once, keeps each
process's host state, stops on a signal to one process with all of them at the same step, and
resumes from that checkpoint as the same run.

Two child processes (this file run as a script) join one CPU run through a coordinator on a free
local port, each with one virtual CPU device and XLA:CPU's fusion emitters off (as in
tests/test_sharding.py); the tests read what they wrote.

A multi-process run is not the single-process run of the same lanes: a process's envs draw the
episode starts (and distractions) of its own lanes from its own seed, where one process draws
those of all lanes from one stream; so the comparison here is of a 2-process run with itself,
uninterrupted and resumed, bit for bit.
"""

from __future__ import annotations

import json
import os
import pathlib
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
FLAGS = f"--xla_force_host_platform_device_count=1 {os.environ['XLA_FLAGS']}"  # conftest's
CUT, END = 160, 200  # frames per seed: evaluations and checkpoints at CUT; the runs end at END
SIGNAL_AT = 35  # the loop step after which process 1 gets SIGTERM (updates start at step 30)


def config(**overrides):
    from test_run import tiny_config

    return tiny_config(eval_every_frames=CUT, checkpoint_every_frames=CUT, **overrides)


def _child(root: pathlib.Path, port: int, process: int) -> None:
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"localhost:{port}", num_processes=2, process_id=process)
    from dear_jax import loop, train
    from dear_jax.signals import Stopped

    assert jax.process_count() == 2 and len(jax.devices()) == 2, jax.devices()
    summaries = {"whole": train.train(config(total_frames=END), root / "whole")}
    step = loop.Loop.step

    def step_then_signal(run, progress):  # only process 1 is told to stop
        step(run, progress)
        if process == 1 and run.carry.counters["iteration"] == SIGNAL_AT:
            os.kill(os.getpid(), signal.SIGTERM)

    loop.Loop.step = step_then_signal
    try:
        train.train(config(total_frames=END), root / "resumed")
    except Stopped as e:
        summaries["stopped"] = str(e)
    loop.Loop.step = step
    summaries["resumed"] = train.train(config(total_frames=END), root / "resumed")
    (root / f"summaries_{process}.json").write_text(json.dumps(summaries))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("multihost")
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, XLA_FLAGS=FLAGS, JAX_PLATFORMS="cpu", MUJOCO_GL="egl")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    children = [
        subprocess.Popen(
            [sys.executable, __file__, str(root), str(port), str(i)],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    outputs = []
    try:
        for child in children:
            outputs.append(child.communicate(timeout=900)[0])
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
    for i, (child, out) in enumerate(zip(children, outputs)):
        assert child.returncode == 0, f"process {i}:\n{out[-5000:]}"
    return root


def test_a_resumed_run_is_the_same_run(runs):
    """SIGTERM to process 1 stops both at the same step with a checkpoint; resumed, the run ends
    as the uninterrupted one: checkpoint arrays (both processes' blocks), process 0's host state,
    replay files and both lanes' logs."""
    from test_run import assert_same_run

    from dear_jax.checkpoint import Checkpointer

    stopped = [json.loads((runs / f"summaries_{i}.json").read_text())["stopped"] for i in (0, 1)]
    # The step after the signal's, 36: 4 frames per seed per step, but for step 21, where the
    # 20-step episodes restarted.
    frame = (SIGNAL_AT + 1 - 1) * 4
    assert stopped[0] == stopped[1]
    assert stopped[0].startswith(f"stopped by SIGTERM at frame {frame} per seed")
    assert frame in Checkpointer(runs / "resumed" / "checkpoints", fingerprint={}).all_steps()

    assert_same_run(runs / "whole", runs / "resumed", END)
    # Process 1's host state (its envs' RNGs, its lanes' returns) is its own, and comes back too.
    extras = [
        json.loads((runs / w / "checkpoints_process_1" / f"{END}.json").read_text())
        for w in ("whole", "resumed")
    ]
    for extra in extras:
        del extra["counters"]["wall_s"]
    assert extras[0] == extras[1]
    mine = json.loads((runs / "whole" / "checkpoints_process_0" / f"{END}.json").read_text())
    assert mine["env_rng"] != extras[0]["env_rng"]


def test_every_lane_is_written_by_its_process(runs):
    from dear_jax.checkpoint import Checkpointer
    from dear_jax.logger import read_csv

    whole = runs / "whole"
    summaries = [json.loads((runs / f"summaries_{i}.json").read_text()) for i in range(2)]
    assert summaries[1]["whole"] == summaries[1]["resumed"] == {}  # process 0 sums up
    summary = summaries[0]["whole"]
    assert summary["processes"] == 2 and summary["devices"] == 2
    assert summary["eval_device"] == "train"  # "auto" with several processes
    assert summary["frames_per_seed"] == END and len(summary["per_seed"]) == 2
    assert summary["updates_per_seed"] >= 5
    chunks = []
    for seed in (0, 1):
        evals = read_csv(whole / f"seed_{seed}" / "eval.csv")
        assert list(evals["frame"]) == [0, CUT, END]
        assert (whole / "videos" / f"eval_{END}_seed_{seed}.mp4").is_file()
        files = sorted((whole / "replay" / f"seed_{seed}").glob("*.npz"))
        assert files
        chunks.append(np.load(files[0]))
    # The lanes learn from different episodes (each process steps its own): the frames their
    # replays stored differ, and each agent kept learning after the checkpoint at CUT.
    assert chunks[0]["frames"].shape == chunks[1]["frames"].shape
    assert not np.array_equal(chunks[0]["frames"], chunks[1]["frames"])
    import jax

    ckpt = Checkpointer(whole / "checkpoints", fingerprint={})
    start, end = (ckpt.read_arrays(frame)["agent"]["params"]["critic"] for frame in (CUT, END))
    first = jax.tree.leaves(end)[0]
    assert first.shape[0] == 2 and not np.array_equal(first[0], first[1])
    for lane in (0, 1):
        assert any(
            not np.array_equal(a[lane], b[lane])
            for a, b in zip(jax.tree.leaves(start), jax.tree.leaves(end))
        )
    assert sorted(p.name for p in whole.glob("run*.lock")) == []  # both locks released


def test_a_run_resumes_only_with_as_many_processes(runs):
    """A 2-process checkpoint holds each process's env host state: one process cannot resume it."""
    from dear_jax import train
    from dear_jax.checkpoint import IncompatibleCheckpointError

    with pytest.raises(IncompatibleCheckpointError, match=r"written by 2 process\(es\), .* has 1;"):
        train.train(config(total_frames=END + 40), runs / "whole")


def test_lanes_that_do_not_split_over_the_processes_are_refused():
    from dear_jax import devices

    with pytest.raises(ValueError, match=r"3 lanes .* cannot be split evenly over 2 processes; "):
        devices.lanes_per_host(3, 2)
    assert devices.lanes_per_host(4, 2) == 2


if __name__ == "__main__":
    _child(pathlib.Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]))
