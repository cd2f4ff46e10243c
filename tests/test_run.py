"""The trainer end to end on CPU: outputs, resume, seeds, and clear errors for bad input."""

import contextlib
import copy
import dataclasses
import functools
import json
import logging
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import types

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from configs import smoke
from dear_jax import (
    evaluations,
    evaluator,
    experiment,
    lanes,
    loop,
    replay,
    replay_disk,
    report,
    train,
    update,
)
from dear_jax.checkpoint import Checkpointer, IncompatibleCheckpointError
from dear_jax.config import load_config, resolve_config_path
from dear_jax.devices import Hosts
from dear_jax.logger import read_csv
from dear_jax.programs import build_programs, hold_keys
from dear_jax.summary import RUNS_PER_GPU_ENV, runs_per_gpu

ROOT = pathlib.Path(__file__).resolve().parents[1]


def tiny_config(**overrides):
    """The smoke config made smaller still: narrow heads, 20-step episodes, a few updates."""
    c = smoke.get_config()
    c.progress = False
    c.total_frames = 200
    c.eval_every_frames = 120
    c.log_every_frames = 40
    c.checkpoint_every_frames = 120
    c.env.episode_frames = 40
    c.agent.batch_size = 4
    c.agent.update_every_steps = 4  # 20 updates per seed in 280 frames
    c.agent.latent_dim = 64
    c.agent.hidden_dim = 32
    c.agent.feature_dim = 8
    c.agent.explore_steps = 40
    c.replay.seed_frames = 120
    c.replay.capacity = 1000
    c.replay.chunk_entries = 40  # 20 rows: the runs write full chunks, not only partial ones
    # One render worker per env (smoke: 2): each is a process forked per env of every run.
    # test_sigterm_checkpoints_exits_cleanly_and_resumes_exactly runs with 2.
    c.env.render.num_workers = 1
    for key, value in overrides.items():
        node = c
        *parents, leaf = key.split(".")
        for part in parents:
            node = node[part]
        node[leaf] = value
    return c


# Columns that hold wall-clock measurements (and the iterations of this process they are per: a
# resumed process counts from its checkpoint); every other column of a resumed run's logs must
# equal the uninterrupted run's.
HOST_STAGES = ("env_action_ms", "env_physics_ms", "env_draw_ms", "env_post_ms", "wait_env_ms")
TIMING_COLUMNS = {
    "fps",
    "wall_s",
    "eval_s",
    "loop_wait_s",
    "sec_per_1000_frames",
    "iteration_ms",
    "iterations",
    *HOST_STAGES,
}


def whole_config():
    """The fixture's uninterrupted run: its loop waits for each evaluation, run by the training's
    programs (eval_device "train"), and it traces a few of its iterations with jax.profiler
    (`config.profile`), where tiny_config's runs evaluate in a background thread on a copy of the
    parameters while training goes on, on the host's CPU (eval_device "auto")."""
    config = tiny_config(total_frames=280, eval_in_background=False, eval_device="train")
    config.profile.at_frame, config.profile.iterations = 160, 3
    return config


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The same experiment run twice: uninterrupted to 280 frames per seed ("whole",
    `whole_config`: evaluating in the foreground, traced), and stopped at 240 (its last
    evaluation and checkpoint) then resumed to 280 on the same workdir (tiny_config). The runs
    share their compiled programs."""
    whole = tmp_path_factory.mktemp("whole")
    train.train(whole_config(), whole)
    workdir = tmp_path_factory.mktemp("run")
    first = train.train(tiny_config(total_frames=240), workdir)
    saved_step = Checkpointer(workdir / "checkpoints", fingerprint={}).latest_step()
    resumed = train.train(tiny_config(total_frames=280), workdir)
    return workdir, first, resumed, saved_step, whole


def assert_same_run(
    a: pathlib.Path, b: pathlib.Path, frame: int, close_columns: set = frozenset()
) -> None:
    """Two workdirs hold the same run: checkpoint `frame` bit for bit (agent, optimisers, keys,
    envs mid-episode, replay counters; host RNG states and loop counters), the replay files, and
    the CSV rows but for wall-clock columns (and `close_columns`, equal to float32 rounding)."""
    arrays = [Checkpointer(w / "checkpoints", fingerprint={}).read_arrays(frame) for w in (a, b)]
    flat = [jax.tree_util.tree_flatten_with_path(x)[0] for x in arrays]
    assert [p for p, _ in flat[0]] == [p for p, _ in flat[1]]
    for (path, x), (_, y) in zip(*flat):
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), jax.tree_util.keystr(path)
    extras = [Checkpointer(w / "checkpoints", fingerprint={}).read_meta(frame)[2] for w in (a, b)]
    for key in ("env_host", "env_rng", "eval_env_rng", "episode_returns", "metric_sum"):
        assert repr(extras[0][key]) == repr(extras[1][key]), key
    for key in ("frame", "iteration", "episode", "updates", "rows"):
        assert extras[0]["counters"][key] == extras[1]["counters"][key], key
    # Full chunks are the same files; partial ones are those of the checkpoints each run keeps.
    files = [{p.relative_to(w) for p in (w / "replay").rglob("*.npz")} for w in (a, b)]
    chunk = tiny_config().replay.chunk_entries // tiny_config().envs_per_seed

    def full(names):
        return {n for n in names if int(n.stem[13:]) - int(n.stem[:12]) == chunk}

    assert full(files[0]) == full(files[1]) and full(files[0])
    for name in sorted(files[0] & files[1]):
        with np.load(a / name) as x, np.load(b / name) as y:
            for field in x.files:
                np.testing.assert_array_equal(x[field], y[field], err_msg=f"{name}:{field}")
    for seed in (0, 1):
        for kind in ("train", "eval"):
            logs = [read_csv(w / f"seed_{seed}" / f"{kind}.csv") for w in (a, b)]
            assert set(logs[0]) == set(logs[1])
            for column in set(logs[0]) - TIMING_COLUMNS - close_columns:
                np.testing.assert_array_equal(logs[0][column], logs[1][column], err_msg=column)
            for column in set(logs[0]) & close_columns:
                np.testing.assert_allclose(logs[0][column], logs[1][column], rtol=1e-6)


def test_outputs_exist_and_parse(run):
    workdir, first, *_ = run
    config = json.loads((workdir / "config.json").read_text())
    assert config["agent"]["method"] == "dear" and config["seeds"] == 2
    for seed in (0, 1):
        train_log = read_csv(workdir / f"seed_{seed}" / "train.csv")
        assert {"frame", "critic_loss", "mask_loss", "ortho_loss", "fps"} <= set(train_log)
        assert np.all(np.isfinite(train_log["frame"]))
        # DEAR's orthogonality loss (the paper's form) is the batch's mean |cos|, logged as such
        np.testing.assert_allclose(train_log["abs_cos_agent_env"], train_log["ortho_loss"], 1e-5)
        # Where an iteration's time went: the env thread's stages and the loop's wait for them
        # happen within the iteration (the env thread's one after the other, so their sum too).
        # Rows that hold a process's compilations have none (below).
        timed = np.isfinite(train_log["iteration_ms"])
        per_iteration = train_log["iteration_ms"][timed]
        stages = np.stack([train_log[k] for k in HOST_STAGES])
        assert not np.isfinite(stages[:, ~timed]).any() and timed.sum() >= 2
        stages = stages[:, timed]
        assert np.all(stages >= 0) and np.all(stages[1:4] > 0)  # every row's steps drew frames
        assert np.all(stages[:4].sum(0) <= per_iteration) and np.all(stages[4] <= per_iteration)
        eval_log = read_csv(workdir / f"seed_{seed}" / "eval.csv")
        assert {
            "episode_return",
            "cos_agent_env",
            "abs_cos_agent_env",
            "fps",
            "sec_per_1000_frames",
        } <= set(eval_log)
        assert np.all(eval_log["abs_cos_agent_env"] >= np.abs(eval_log["cos_agent_env"]))
        assert list(eval_log["frame"][:3]) == [0, 120, 240]  # frame 0: the untrained policy
        assert any((workdir / f"seed_{seed}" / "tb").iterdir())
    # One process's log: its first row and that of its first update (the compilations) untimed.
    whole_log = read_csv(run[-1] / "seed_0" / "train.csv")
    first_update = np.flatnonzero(whole_log["updates"] > 0)[0]
    assert first_update > 0
    untimed = np.flatnonzero(~np.isfinite(whole_log["iteration_ms"]))
    np.testing.assert_array_equal(untimed, [0, first_update])
    video = workdir / "videos" / "eval_240_seed_0.mp4"
    cap = cv2.VideoCapture(str(video))
    ok, frame = cap.read()
    assert ok and frame.shape[1] >= 3 * frame.shape[0]  # RGB | true mask | predicted mask
    curves = cv2.imread(str(workdir / "curves.png"))  # drawn at the run's end
    assert curves is not None and curves.shape[0] > 100 and curves.std() > 0
    text = (workdir / "summary.md").read_text()
    assert text.startswith("# dear on walker-walk") and "; no distraction;" in text
    summary = json.loads((workdir / "summary.json").read_text())  # rewritten by the resume
    assert summary["frames_per_seed"] == 280 and len(summary["per_seed"]) == 2
    assert (summary["distraction_types"], summary["backgrounds"]) == ([], "none")
    assert summary["replay_sampling"] == "uniform" and "sampled by episode" not in text
    assert (summary["conv_stack"], summary["kernels"]) == ("xla", "")
    assert summary["render"]["gpus"] == "auto"  # no GPU here: MuJoCo's EGL chooses
    assert "(cpu physics, xla conv stacks, evaluations on" in text
    # Where the iterations went: the train log's stages, seed 0's rows averaged.
    stages = summary["host_ms_per_iteration"]
    seed0 = read_csv(workdir / "seed_0" / "train.csv")
    timed = np.isfinite(seed0["env_draw_ms"])
    draw = np.average(seed0["env_draw_ms"][timed], weights=seed0["iterations"][timed])
    assert stages["env_draw_ms"] == pytest.approx(draw)
    assert f"{stages['iteration_ms']:.1f} ms an iteration: the env waited " in text
    # Where the run comes from: this checkout's commit, the device, the library versions.
    import jax

    from dear_jax.provenance import commit

    provenance = summary["provenance"]
    assert provenance["commit"] == commit() != "unknown"
    assert (provenance["jax"], provenance["platform"]) == (jax.__version__, "cpu")
    import flax
    import mujoco

    versions = f"jax {jax.__version__}, flax {flax.__version__}, mujoco {mujoco.__version__}"
    assert versions in text  # summary.md names them, as summary.json does
    assert summary["stopped"] is None
    assert summary["eval_device"] == "cpu"  # "auto", resolved on this CPU-only machine
    assert first["frames_per_seed"] == 240


def test_provenance_records_xla_flags_and_the_egl_device_only_where_set(monkeypatch):
    from dear_jax.provenance import provenance

    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("MUJOCO_EGL_DEVICE_ID", raising=False)
    assert not {"xla_flags", "mujoco_egl_device_id"} & set(provenance())
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_enable_triton_gemm=false")
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "1")
    assert provenance()["xla_flags"] == "--xla_gpu_enable_triton_gemm=false"
    assert provenance()["mujoco_egl_device_id"] == "1"


def test_frames_and_updates_follow_the_papers_ratio(run):
    """Frames count per seed over its E envs; one update per 2 agent steps after seed frames."""
    workdir, first, resumed, *_ = run
    c = tiny_config()
    frames_per_step = c.envs_per_seed * c.env.action_repeat  # one loop iteration, per seed
    steps_learned = (240 - c.replay.seed_frames) // frames_per_step * c.envs_per_seed
    assert first["updates_per_seed"] == steps_learned // c.agent.update_every_steps
    resumed_steps = (280 - 240) // frames_per_step * c.envs_per_seed
    assert resumed["updates_per_seed"] == (
        first["updates_per_seed"] + resumed_steps // c.agent.update_every_steps
    )
    # An episode of episode_frames per env is E x episode_frames frames of its seed (the resumed
    # run continues the episodes under way).
    log = read_csv(workdir / "seed_0" / "train.csv")
    assert len(log["frame"]) >= 5 and log["frame"][-1] > 240
    episode = c.env.episode_frames * c.envs_per_seed
    np.testing.assert_array_equal(log["episode"], log["frame"] // episode)


def test_resume_continues_from_saved_step(run):
    workdir, first, resumed, saved_step, _ = run
    assert saved_step == 240
    assert resumed["frames_per_seed"] == 280
    frames = read_csv(workdir / "seed_0" / "eval.csv")["frame"]
    assert list(frames) == [0, 120, 240, 280]  # no frame evaluated twice, none lost
    assert (
        sorted(p.name for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())[-1] == "280"
    )


def test_a_checkpoint_does_not_wait_for_the_evaluation_starting_at_its_frame(run):
    """The first run's last checkpoint (240) falls on an evaluation's frame: saved before that
    evaluation started, it holds it as due, and the resumed run evaluated there once more,
    replacing the first run's row (its rows equal the uninterrupted run's:
    test_resumed_run_equals_the_uninterrupted_one)."""
    workdir, *_ = run
    _, _, extra = Checkpointer(workdir / "checkpoints", fingerprint={}).read_meta(240)
    assert (extra["loop"]["last_eval_frame"], extra["loop"]["next_eval"]) == (120, 240)
    for seed in (0, 1):
        frames = read_csv(workdir / f"seed_{seed}" / "eval.csv")["frame"].tolist()
        assert frames == [0, 120, 240, 280]


def test_seeds_differ(run):
    """Each seed has its own episodes and exploration, not only its own initial parameters: the
    frames and actions its replay stored differ from the other seed's, and so do its losses."""
    workdir = run[0]
    a = read_csv(workdir / "seed_0" / "train.csv")
    b = read_csv(workdir / "seed_1" / "train.csv")
    assert not np.allclose(a["critic_loss"], b["critic_loss"], equal_nan=True)
    c = tiny_config()
    chunk = replay_disk.chunk_rows_for(c.replay.chunk_entries, c.envs_per_seed, 10**9)
    first = [
        np.load(workdir / "replay" / f"seed_{s}" / replay_disk.file_name(0, chunk)) for s in (0, 1)
    ]
    assert set(first[0].files) == set(first[1].files)
    for key in ("frames", "actions"):
        assert first[0][key].shape == first[1][key].shape
        assert not np.array_equal(first[0][key], first[1][key]), key


def test_resumed_run_equals_the_uninterrupted_one(run):
    """Stopped at 240 frames and resumed, the run ends where the uninterrupted one does."""
    workdir, *_, whole = run
    assert_same_run(whole, workdir, 280)
    # Replay chunks are written as they fill; a checkpoint adds the unfinished chunk's rows.
    c = tiny_config()
    chunk = replay_disk.chunk_rows_for(c.replay.chunk_entries, c.envs_per_seed, 10**9)
    names = [p.name for p in (workdir / "replay" / "seed_0").iterdir()]
    assert replay_disk.file_name(0, chunk) in names and len(names) >= 3


def test_a_finished_run_rerun_does_nothing_but_print_its_summary(run, tmp_path, monkeypatch):
    """Rerun with the config it finished under, a run that trained to total_frames and ran its
    closing evaluation builds nothing and changes no file: it returns its summary. Trained
    further (a larger total_frames), or stopped before its summary said it finished (a signal,
    or killed before the closing evaluation ended), it resumes."""
    workdir = tmp_path / "done"
    shutil.copytree(run[0], workdir)
    files = {p: p.read_bytes() for p in workdir.rglob("*") if p.is_file()}

    def no_env(*args, **kwargs):
        raise AssertionError("a finished run built its envs")

    monkeypatch.setattr(train, "make_env", no_env)
    summary = train.train(tiny_config(total_frames=280), workdir)
    assert summary == json.loads((workdir / "summary.json").read_text())
    assert summary["frames_per_seed"] == 280 and summary["stopped"] is None
    assert {p: p.read_bytes() for p in workdir.rglob("*") if p.is_file()} == files
    ckpt = Checkpointer(workdir / "checkpoints", fingerprint={})
    assert train._finished(tiny_config(total_frames=320), workdir, ckpt) is None
    for changed in ({"stopped": "SIGTERM"}, {"frames_per_seed": 240}):
        (workdir / "summary.json").write_text(json.dumps({**summary, **changed}))
        assert train._finished(tiny_config(total_frames=280), workdir, ckpt) is None


def test_evaluating_in_the_foreground_and_tracing_change_nothing_but_timing(run):
    """The fixture's stopped and resumed run evaluates in a background thread on a copy of the
    parameters while training goes on, on the host's CPU (eval_device "auto"); its uninterrupted
    run, whose loop waits for each evaluation, run by the training's programs (eval_device
    "train"), and traces a few of its iterations with jax.profiler (`whole_config`), logs the
    same eval rows and trains exactly the same run, and leaves the trace in workdir/profile."""
    workdir, *_, whole = run
    assert json.loads((whole / "summary.json").read_text())["eval_device"] == "train"
    assert_same_run(whole, workdir, 280)
    assert len(read_csv(whole / "seed_0" / "eval.csv")["frame"]) >= 3
    assert len(list((whole / "profile").rglob("*.xplane.pb"))) == 1


def test_background_evaluations_queue_without_holding_up_the_loop(run, tmp_path, monkeypatch):
    """The evaluation at frame 0 is held until the loop first waits for an evaluation: the loop
    starts the one at 120 beside it, and waits only at 240, with MAX_PENDING_EVALS (2) started
    and unlogged. The run, rows included, is the uninterrupted fixture run's."""
    loop_waits, held, waited = threading.Event(), [], []
    evaluate, finish = evaluator.LocalEvaluator.evaluate, evaluations.Evaluations.finish

    def held_evaluate(self, params, key, **kwargs):
        if not held:  # the first evaluation, at frame 0
            held.append(loop_waits.wait(timeout=600))
        return evaluate(self, params, key, **kwargs)

    def watched_finish(self, *, keep=None):
        if keep is not None and len(self.pending) > keep and not waited:
            waited.append((self.carry.counters["frame"], len(self.pending)))
            loop_waits.set()
        finish(self, keep=keep)

    monkeypatch.setattr(evaluator.LocalEvaluator, "evaluate", held_evaluate)
    monkeypatch.setattr(evaluations.Evaluations, "finish", watched_finish)
    # No checkpoint at 120: a checkpoint waits for every evaluation in flight.
    config = tiny_config(total_frames=280, eval_device="train", checkpoint_every_frames=0)
    train.train(config, tmp_path)
    assert evaluations.MAX_PENDING_EVALS == 2
    assert held == [True] and waited == [(240, 2)]
    assert_same_run(run[-1], tmp_path, 280)


def test_report_evals_sets_evaluations_against_the_training_between_them(run):
    """`report evals` on the fixture's run (evaluations in the background, 2 seeds): every
    figure recomputed from its logs; the loop's waits are logged with each evaluation."""
    workdir = run[0]
    (row,) = report.eval_rows([workdir])
    evals = read_csv(workdir / "seed_0" / "eval.csv")
    train_log = read_csv(workdir / "seed_0" / "train.csv")
    assert list(evals["frame"]) == [0, 120, 240, 280] and (evals["loop_wait_s"] >= 0).all()
    assert row["eval_s"] == pytest.approx(np.median(evals["eval_s"][1:]))
    # 120 -> 240 is a whole interval; 240 -> 280 (the closing evaluation) is not
    assert row["between_s"] == pytest.approx(evals["wall_s"][2] - evals["wall_s"][1])
    # The training's rate: of the rows in whose span no evaluation started (an evaluation at a
    # row's own frame starts after that row is logged: it is in the next row's span).
    clean, since = [], 0
    for frame, fps in zip(train_log["frame"], train_log["fps"]):
        if np.isfinite(fps) and not any(since <= e < frame for e in evals["frame"]):
            clean.append(fps)
        since = frame
    assert 0 < len(clean) < np.isfinite(train_log["fps"]).sum()
    assert row["train_s"] == pytest.approx(120 * 2 / np.median(clean))
    # Rows holding a checkpoint (every 120 frames: at 120 and 240): their time beyond the rate.
    excess, since = 0.0, 0
    for frame, fps in zip(train_log["frame"], train_log["fps"]):
        if np.isfinite(fps) and any(since <= c < frame for c in (120, 240)):
            excess += (frame - since) * 2 / fps - (frame - since) * 2 / np.median(clean)
        since = frame
    assert row["checkpoint_excess_s"] == pytest.approx(excess)
    wall = json.loads((workdir / "summary.json").read_text())["wall_s"]
    assert row["loop_wait_s"] == pytest.approx(evals["loop_wait_s"].sum())
    assert row["loop_wait_share"] == pytest.approx(evals["loop_wait_s"].sum() / wall)
    assert (row["lanes"], row["eval_processes"], row["method"]) == (2, 1, "dear")
    _, text = report.evals_table([workdir])
    assert f"| {workdir.name} " in text and f"{row['train_s']:.1f}" in text


def test_runs_beside_others_on_their_gpu_are_counted_from_the_environment(monkeypatch):
    """$DEAR_JAX_RUNS_PER_GPU (set by `dear_jax.grid --per-gpu`) is how many runs train side by
    side on a run's GPU: 1 when unset; anything but a count >= 1 is refused by name."""
    monkeypatch.delenv(RUNS_PER_GPU_ENV, raising=False)
    assert runs_per_gpu() == 1
    monkeypatch.setenv(RUNS_PER_GPU_ENV, "3")
    assert runs_per_gpu() == 3
    for bad in ("0", "two", "-1", ""):
        monkeypatch.setenv(RUNS_PER_GPU_ENV, bad)
        with pytest.raises(ValueError, match=f"DEAR_JAX_RUNS_PER_GPU='{bad}': give how many"):
            runs_per_gpu()


def test_evaluations_in_two_processes_log_what_one_evaluator_logs(run, tmp_path, monkeypatch):
    """eval_processes=2: the evaluations at frames 0 and 240 (and the closing one at 280) run in
    one process, the one at 120 in the other, side by side. Stopped at 240 and resumed to 280
    (both processes' eval-env states restored from the checkpoint). Without distractions an
    evaluation's episodes follow from its key alone, so every eval row and every training row is
    the uninterrupted fixture run's."""
    streams, evaluate = [], evaluator.EvalProcess.evaluate

    def counted(self, *args, **kwargs):
        streams.append(self.stream)
        return evaluate(self, *args, **kwargs)

    monkeypatch.setattr(evaluator.EvalProcess, "evaluate", counted)
    monkeypatch.setenv(RUNS_PER_GPU_ENV, "2")  # as the grid starts a job beside another
    for frames in (240, 280):
        train.train(tiny_config(total_frames=frames, eval_device="cpu", eval_processes=2), tmp_path)
    # 0, 120, 240; resumed: 240 again (its checkpoint, saved first, holds it as due), 280
    assert streams[:2] in ([0, 1], [1, 0]) and streams[2:] == [0, 0, 0]
    whole = run[-1]
    for seed in (0, 1):
        for kind in ("train", "eval"):
            logs = [read_csv(w / f"seed_{seed}" / f"{kind}.csv") for w in (whole, tmp_path)]
            assert set(logs[0]) == set(logs[1])
            for column in set(logs[0]) - TIMING_COLUMNS:
                np.testing.assert_array_equal(logs[0][column], logs[1][column], err_msg=column)
    assert list(read_csv(tmp_path / "seed_0" / "eval.csv")["frame"]) == [0, 120, 240, 280]
    assert report.eval_rows([tmp_path])[0]["eval_processes"] == 2  # from the summary
    text = (tmp_path / "summary.md").read_text()
    assert "evaluations on cpu, 2 processes; 2 runs side by side on this device)" in text
    assert json.loads((tmp_path / "summary.json").read_text())["runs_per_gpu"] == 2
    ckpt = Checkpointer(tmp_path / "checkpoints", fingerprint={})
    saved = ckpt.read_meta(ckpt.latest_step())[2]["eval_env_rng"]
    states = evaluator.eval_states(saved)
    assert len(states) == 2 and repr(states[0]) != repr(states[1])


def test_the_evaluation_processes_run_their_policy_where_the_resolved_eval_device_says(
    monkeypatch,
):
    """eval_device "auto" resolved to "accelerator" reaches the evaluation processes (their
    policy on the accelerator, not the config's unresolved "auto"), one or several."""
    made = []
    monkeypatch.setattr(train, "EvalProcess", lambda config, **kw: made.append((1, kw)))
    monkeypatch.setattr(
        train, "EvalProcesses", lambda config, count, **kw: made.append((count, kw))
    )
    config = tiny_config()
    assert config.eval_device == "auto"
    for count in (1, 2):
        train._evaluator(config, "accelerator", count, None, None, Hosts(None, config.seeds))
    assert made == [(1, {"policy_on": "accelerator"}), (2, {"policy_on": "accelerator"})]
    with pytest.raises(ValueError, match="policy_on='auto': valid: cpu, accelerator"):
        evaluator.EvalProcess(config, policy_on="auto")


def test_evaluation_processes_restore_states_saved_by_fewer_or_more():
    """A checkpoint's eval-env state restores into N evaluation processes whatever wrote it: a
    single evaluator's state goes to the first process, the others keep their own streams; a
    list of more is cut to N."""

    class Process:
        def __init__(self, name):
            self.state = f"{name} fresh"

        def set_host_state(self, state):
            self.state = state

    pool = evaluator.EvalProcesses.__new__(evaluator.EvalProcesses)
    pool.processes, pool.slots = [Process("a"), Process("b")], 2
    pool.set_host_state({"episode_rng": "x"})
    assert [p.state for p in pool.processes] == [{"episode_rng": "x"}, "b fresh"]
    pool.set_host_state({"processes": ["s0", "s1", "s2"]})
    assert [p.state for p in pool.processes] == ["s0", "s1"]
    assert [pool.evaluator_for(i) for i in range(3)] == [*pool.processes, pool.processes[0]]
    assert evaluator.eval_states({"processes": ["s0"]}) == ["s0"]
    assert evaluator.eval_states({"episode_rng": "x"}) == [{"episode_rng": "x"}]


def test_the_segmentation_pass_is_drawn_only_where_something_reads_the_labels():
    """The render pool draws the segmentation pass where the method's loss reads the agent's
    mask (DEAR, SEAR), where distractions composite backgrounds, and in the eval env for the env
    whose videos show the true mask (env 0 of each seed; every env where backgrounds are
    composited); DrQ-v2 and TED training envs without distraction skip it, and their masks are
    all 0. The frames are the same either way."""
    key = jax.random.key(0)

    def first_step(eval_env=False, **overrides):
        config = tiny_config(**overrides)
        if eval_env:
            env = experiment.make_eval_env(config)
        else:
            env = experiment.make_env(config, envs_per_seed=1, split="train", seed=0)
        try:
            return env.render_settings.labels, env.reset(key)[1]
        finally:
            env.close()

    dear_labels, dear = first_step(**{"agent.method": "dear"})
    assert dear_labels and np.asarray(dear.true_mask).any()
    assert first_step(**{"agent.method": "sear"})[0]
    for method in ("drqv2", "ted"):
        labels, ts = first_step(**{"agent.method": method})
        assert not labels and not np.asarray(ts.true_mask).any()
        np.testing.assert_array_equal(ts.frame, dear.frame)
    assert first_step(**{"agent.method": "drqv2", "env.distraction": "easy"})[0]
    # The eval env: 2 envs per seed (episodes), the true mask in env 0's video only.
    for method in ("drqv2", "dear"):
        overrides = {"agent.method": method, "num_eval_episodes": 2}
        labels, ts = first_step(eval_env=True, **overrides)
        mask = np.asarray(ts.true_mask)
        assert labels and mask[:, 0].any(axis=(1, 2)).all() and not mask[:, 1].any()
        labels, unlabelled = first_step(eval_env=True, save_video=False, **overrides)
        assert not labels and not np.asarray(unlabelled.true_mask).any()
        np.testing.assert_array_equal(unlabelled.frame, ts.frame)
    overrides = {"agent.method": "drqv2", "env.distraction": "easy", "num_eval_episodes": 2}
    labels, ts = first_step(eval_env=True, **overrides)  # composited: every env's labels
    assert labels and np.asarray(ts.true_mask).any(axis=(2, 3)).all()


def test_where_the_evaluation_runs_by_default_and_when_told(monkeypatch):
    """eval_device "auto" is a process of its own when the run has one process: on the GPU
    with a GPU, else on the host's CPU, where its policy runs in float32 whatever
    agent.compute_dtype says (its actions those of the bf16 program up to bf16's rounding);
    "train" keeps the training's devices and dtype."""
    config = tiny_config(**{"agent.compute_dtype": "bfloat16"})
    hosts = Hosts(None, config.seeds)
    assert experiment.eval_device(config, hosts) == "cpu"
    with monkeypatch.context() as m:
        m.setattr(jax, "default_backend", lambda: "gpu")
        assert experiment.eval_device(config, hosts) == "accelerator"
    config.eval_device = "train"
    assert experiment.eval_device(config, hosts) == "train"
    # Several processes (jax.distributed) evaluate in the training processes, and only there.
    two = types.SimpleNamespace(multi=True, count=2)
    for own in ("cpu", "accelerator"):
        config.eval_device = own
        with pytest.raises(ValueError, match=f"eval_device='{own}' evaluates in one process"):
            experiment.eval_device(config, two)
    config.eval_device = "auto"
    assert experiment.eval_device(config, two) == "train"
    # Evaluation processes side by side are processes of their own; by default (0) two beside
    # a training on a GPU, else one.
    assert config.eval_processes == 0
    places = ("accelerator", "cpu", "train")
    assert {w: experiment.eval_processes(config, w) for w in places} == dict.fromkeys(places, 1)
    with monkeypatch.context() as m:
        m.setattr(jax, "default_backend", lambda: "gpu")
        counts = {w: experiment.eval_processes(config, w) for w in places}
    assert counts == {"accelerator": 2, "cpu": 2, "train": 1}
    config.eval_processes = 2
    with pytest.raises(ValueError, match="eval_processes=2 evaluates in processes of their own"):
        experiment.eval_device(config, two)
    assert experiment.eval_device(config, hosts) == "cpu"
    assert experiment.eval_processes(config, "cpu") == 2
    told = copy.deepcopy(config)
    told.eval_device = "train"  # refused before the run starts, not once it has built its envs
    with pytest.raises(ValueError, match="eval_processes=2 evaluates in processes of their own"):
        experiment.validate(told)
    told.eval_device = "auto"
    experiment.validate(told)
    config.eval_processes = -1
    with pytest.raises(ValueError, match="eval_processes must be an int >= 1, or 0 .*got -1"):
        experiment.validate(config)
    config.eval_processes = 1
    config.eval_nice = 20
    with pytest.raises(ValueError, match=r"eval_nice must be an int in 0-19 .*got 20"):
        experiment.validate(config)
    config.eval_nice = 0
    # Values a run would fail on later (or loop on) are refused before it starts, by name.
    for key, bad, match in [
        ("agent.compute_dtype", "float99", "unknown agent.compute_dtype 'float99'; valid: float32"),
        ("env.render.quality", "bogus", "unknown env.render.quality 'bogus'; valid: dm_control"),
        ("env.action_repeat", 0, "env.action_repeat must be >= 1, got 0"),
        ("keep_checkpoints", 0, "keep_checkpoints must be >= 1, got 0"),
        ("log_every_frames", 0, "log_every_frames must be >= 1, got 0"),
        ("checkpoint_every_frames", -40, r"checkpoint_every_frames must be >= 0 \(0: no periodic"),
        ("replay.chunk_entries", 0, "replay.chunk_entries must be >= 1, got 0"),
        (
            "replay.sampling",
            "episodes",
            "unknown replay.sampling 'episodes'; valid: uniform, episode",
        ),
        ("env.render.num_workers", -1, "env.render: num_workers must be 0 .auto. or more"),
        ("agent.encoder", "plain", "agent: method 'dear' needs encoder='pool'"),
        ("agent.discount", 1.5, r"agent.discount must be in \(0, 1\], got 1.5"),
        ("agent.tau", 0.0, r"agent.tau must be a finite number in \(0, 1\], got 0"),
        ("agent.beta", float("nan"), "agent.beta must be a finite number, got nan"),
        ("agent.std_steps", 0, "agent.std_steps must be a whole number >= 1, got 0"),
        ("agent.hidden_dim", -4, "agent.hidden_dim must be >= 1, got -4"),
        ("agent.latent_dim", 0, "agent.latent_dim must be >= 1, got 0"),
        ("agent.lr", -1e-4, r"agent.lr must be in \(0, inf\], got -0.0001"),
        ("agent.stddev_clip", -0.3, "agent.stddev_clip must be a finite number >= 0, got -0.3"),
        ("env.mask_drop_prob", 2.0, r"env.mask_drop_prob must be in \[0, 1\], got 2.0"),
        ("env.episode_frames", -5, r"env.episode_frames must be >= 0 \(0: the task's own\)"),
        # the tiny config's 40-frame episodes, and below walker's own 1,000 (episode_frames 0)
        ("env.action_repeat", 3, "env.action_repeat=3 does not divide env.episode_frames of 40"),
        (
            "replay.capacity",
            6,
            r"replay.capacity=6 holds 3 steps of envs_per_seed=2 envs: .* above 6",
        ),
        ("agent.updates_per_call", -1, r"agent.updates_per_call must be an int >= 1, or 0 \(on"),
        ("agent.xla_options", "CONCURRENT", "'CONCURRENT': give NAME=VALUE, NAME an XLA option"),
        # XLA's own error, named
        ("agent.xla_options", "xla_no_such=1", "agent.xla_options='xla_no_such=1': .*xla_no_such"),
    ]:
        bad_config = copy.deepcopy(config)
        *parents, field = key.split(".")
        node = bad_config
        for part in parents:
            node = node[part]
        node[field] = bad
        with pytest.raises(ValueError, match=match):
            experiment.validate(bad_config)
    own = copy.deepcopy(config)
    own.env.episode_frames, own.env.action_repeat = 0, 3
    with pytest.raises(ValueError, match="does not divide walker-walk's episode of 1000 frames"):
        experiment.validate(own)
    assert experiment.eval_processes(config, "accelerator") == 1
    config.eval_device = "train"
    acfg = experiment.agent_config(config, action_dim=6)
    programs = build_programs(acfg, experiment.hparams(config), config)
    params = update.init_seeds(acfg, jax.random.split(jax.random.key(0), config.seeds)).params
    obs = jax.random.randint(jax.random.key(1), (config.seeds, 3, 84, 84, 9), 0, 256, jnp.uint8)
    host = jax.make_jaxpr(programs.evaluate_step_host)(params, obs)
    trained = jax.make_jaxpr(programs.evaluate_step)(params, obs)
    assert "bf16" in str(trained) and "bf16" not in str(host)
    (a_host, cos_host, pred_host), (a, cos, pred) = (
        step(params, obs) for step in (programs.evaluate_step_host, programs.evaluate_step)
    )
    assert a_host.shape == a.shape == (config.seeds, 3, 6) and pred_host.shape == (2, 84, 84)
    np.testing.assert_allclose(a_host, a, atol=0.03)
    np.testing.assert_allclose(pred_host, pred, atol=0.03)
    assert not np.array_equal(a_host, a)  # two programs, not one


def test_the_loops_act_holds_each_lanes_draws_by_its_hold_key():
    """programs.act with the lanes' hold keys (what the loop passes): with noise_hold 3, two
    steps of one block act alike whatever their keys, and by the hold keys given; with
    noise_hold 1 the keys change nothing (every step draws from its own key)."""
    fixed = {"agent.explore_steps": 0, "agent.std_init": 0.5, "agent.std_final": 0.5}
    config = tiny_config(seeds=2, **{"agent.noise_hold": 3, **fixed})
    acfg = experiment.agent_config(config, action_dim=6)
    agent = update.init_seeds(acfg, jax.random.split(jax.random.key(0), config.seeds))
    obs = jax.random.randint(jax.random.key(1), (config.seeds, 3, 84, 84, 9), 0, 256, jnp.uint8)
    stepping = jnp.ones((config.seeds, 3), bool)
    keys = hold_keys(config)

    def actions(config, steps, key, hold):
        programs = build_programs(acfg, experiment.hparams(config), config)
        state = jax.tree.map(jnp.copy, agent)  # act donates the agent it is given
        state = state.replace(steps=jnp.full((config.seeds,), steps, jnp.int32))
        return np.asarray(programs.act(state, obs, jax.random.key(key), stepping, hold)[0])

    first, second = actions(config, 0, 5, keys), actions(config, 3, 6, keys)  # per env: 0, 1
    np.testing.assert_array_equal(first, second)
    assert not np.allclose(first, actions(config, 9, 6, keys), atol=1e-3)  # per env 3: next
    assert not np.allclose(first, actions(config, 0, 5, keys[::-1]), atol=1e-3)  # the lanes' keys
    config.agent.noise_hold = 1
    np.testing.assert_array_equal(actions(config, 0, 5, keys), actions(config, 0, 5, None))


def test_the_updates_sample_the_replay_as_replay_sampling_says(monkeypatch):
    """programs.learn hands replay.sampling to the sampler: "episode" draws by episode, in a
    later run of the same process too (`benchmarks.train --vary replay.sampling ...`)."""
    told = []

    def sample(*args, by_episode=False, **kwargs):
        told.append(by_episode)
        return replay_sample(*args, by_episode=by_episode, **kwargs)

    replay_sample = replay.sample
    monkeypatch.setattr(replay, "sample", sample)
    config = tiny_config(seeds=1)
    acfg = experiment.agent_config(config, action_dim=6)
    agent = update.init_seeds(acfg, jax.random.split(jax.random.key(0), 1))
    buffer = replay.init(64, 3, (84, 84, 3), 6, leading=(1,))
    for sampling in ("uniform", "episode"):  # as two runs of one process get them
        config.replay.sampling = sampling
        programs = loop.cached_programs(acfg, config)
        # traced as a top-level jit: a nested one may not take the program's compiler options
        programs.learn.trace(agent, buffer, jax.random.key(1))
    assert told == [False, True]


def test_ted_form_reaches_the_sampler_and_the_loss(monkeypatch):
    """agent.ted_form from the config to what it changes: the replay's same-episode draws
    (skip_positives) and the loss's missing negatives (substitute)."""
    told = {"sample": [], "loss": []}

    def sample(*args, skip_positives=True, **kwargs):
        told["sample"].append(skip_positives)
        return replay_sample(*args, skip_positives=skip_positives, **kwargs)

    def loss(*args, substitute=False, **kwargs):
        told["loss"].append(substitute)
        return ted_loss(*args, substitute=substitute, **kwargs)

    replay_sample, ted_loss = replay.sample, update.ted_classifier_loss
    monkeypatch.setattr(replay, "sample", sample)
    monkeypatch.setattr(update, "ted_classifier_loss", loss)
    buffer = jax.eval_shape(lambda: replay.init(64, 3, (84, 84, 3), 6, leading=(1,)))
    for form in ("strict", "reference_code"):
        config = tiny_config(seeds=1, **{"agent.method": "ted", "agent.ted_form": form})
        acfg = experiment.agent_config(config, action_dim=6)
        agent = jax.eval_shape(functools.partial(update.init_seeds, acfg), jax.random.key(0)[None])
        programs = build_programs(acfg, experiment.hparams(config), config)
        programs.learn.trace(agent, buffer, jax.random.key(1))
    assert told == {"sample": [True, False], "loss": [False, True]}


def test_updates_per_call_0_is_an_iterations_updates_on_a_gpu(monkeypatch):
    """agent.updates_per_call 0 (the default): on a GPU all of an iteration's updates a call
    (envs_per_seed / update_every_steps, at least 1), on a CPU one; a number is itself."""
    config = tiny_config(envs_per_seed=16, **{"agent.update_every_steps": 2})
    assert config.agent.updates_per_call == 0
    assert experiment.updates_per_call(config) == 1  # this CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert experiment.updates_per_call(config) == 8
    config.agent.update_every_steps = 32
    assert experiment.updates_per_call(config) == 1
    config.agent.updates_per_call = 3
    assert experiment.updates_per_call(config) == 3
    assert experiment.xla_options(" xla_a=1, xla_b=X ,") == {"xla_a": "1", "xla_b": "X"}


def test_updates_per_call_hands_each_call_its_updates_keys(tmp_path, monkeypatch):
    """agent.updates_per_call 2: the loop's 2 updates of an iteration (2 envs, an update per
    agent step) go to one call with their 2 keys, and count as 2. With each call's updates made
    one by one by the one-update program (so that no scan compiles: its own program is checked
    to be a scan of 2 `learn`s), the run is the one of one update per call: its evaluations
    alike, its logged losses to the rounding of their sums."""
    overrides = {"agent.update_every_steps": 1}
    config = tiny_config(**overrides, **{"agent.updates_per_call": 2})
    acfg = experiment.agent_config(config, action_dim=6)
    learn = build_programs(acfg, experiment.hparams(config), config).learn
    init = functools.partial(update.init_seeds, acfg)
    agent = jax.eval_shape(init, jax.random.split(jax.random.key(0), 2))
    buffer = jax.eval_shape(lambda: replay.init(64, 3, (84, 84, 3), 6, leading=(2,)))
    keys = jax.random.split(jax.random.key(1), 2)
    inner = [e for e in learn.trace(agent, buffer, keys).jaxpr.eqns if e.primitive.name == "scan"]
    assert [e.params["length"] for e in inner] == [2]
    real = loop.cached_programs
    calls = []

    def one_by_one(acfg, config, mesh=None):
        one = real(acfg, tiny_config(**overrides), mesh)

        def learn(agent, buffer, keys):
            calls.append(keys.shape)
            metrics = []
            for key in keys:
                agent, m = one.learn(agent, buffer, key)
                metrics.append(m)
            return agent, jax.tree.map(lambda *m: sum(m), *metrics)

        return dataclasses.replace(one, learn=learn)

    train.train(tiny_config(**overrides), tmp_path / "1")
    monkeypatch.setattr(loop, "cached_programs", one_by_one)
    train.train(config, tmp_path / "2")
    assert calls and set(calls) == {(2,)}
    logs = [read_csv(tmp_path / n / "seed_0" / "train.csv") for n in ("1", "2")]
    done = [json.loads((tmp_path / n / "summary.json").read_text()) for n in ("1", "2")]
    assert done[0]["updates_per_seed"] == done[1]["updates_per_seed"] == 2 * len(calls) > 2
    np.testing.assert_array_equal(logs[1]["updates"], logs[0]["updates"])
    for key in ("critic_loss", "mask_loss", "ortho_loss", "q1", "actor_loss"):  # summed anew
        np.testing.assert_allclose(logs[1][key], logs[0][key], rtol=1e-6, err_msg=key)
    returns = [read_csv(tmp_path / n / "seed_1" / "eval.csv")["episode_return"] for n in "12"]
    np.testing.assert_array_equal(*returns)  # the same updates made: the same agent
    # 3 a call where an iteration owes 2: whole calls only, the rest owed to the next iteration.
    calls.clear()
    train.train(tiny_config(**overrides, **{"agent.updates_per_call": 3}), tmp_path / "3")
    made = json.loads((tmp_path / "3" / "summary.json").read_text())["updates_per_seed"]
    assert set(calls) == {(3,)} and made == 3 * len(calls)
    assert done[0]["updates_per_seed"] - 2 <= made <= done[0]["updates_per_seed"]


def test_table_ii_is_computed_from_the_trainers_logs(run, tmp_path):
    """`python -m dear_jax.report table` on a run the trainer wrote: every number recomputed here
    from that run's CSVs, summary and config."""
    whole = run[-1]
    threshold = 1.0
    rows, text = report.runs_table([whole], threshold, out=str(tmp_path / "table"))
    (row,) = rows
    c = tiny_config(total_frames=280)
    evals = [read_csv(whole / f"seed_{s}" / "eval.csv") for s in range(c.seeds)]
    finals = np.array([e["episode_return"][-1] for e in evals])
    assert row["final_return_mean"] == pytest.approx(finals.mean())
    assert row["final_return_std"] == pytest.approx(finals.std())
    assert all(len(e["frame"]) > 2 for e in evals)
    lasts = np.array([e["episode_return"][-2:].mean() for e in evals])
    (two,) = report.run_rows(whole, threshold, last=2)
    assert two["last_return_mean"] == pytest.approx(lasts.mean())
    assert two["last_return_std"] == pytest.approx(lasts.std())
    all_of = np.array([e["episode_return"].mean() for e in evals])  # fewer than 11 there
    assert row["last_return_mean"] == pytest.approx(all_of.mean()) and row["last"] == 11
    with pytest.raises(ValueError, match="last must be at least 1"):
        report.run_rows(whole, threshold, last=0)
    assert row["cos"] == pytest.approx(np.mean([e["cos_agent_env"][-1] for e in evals]))
    assert row["abs_cos"] == pytest.approx(np.mean([e["abs_cos_agent_env"][-1] for e in evals]))
    firsts = [e["frame"][np.argmax(e["episode_return"] >= threshold)] for e in evals]
    reaching = [f for f, e in zip(firsts, evals) if (e["episode_return"] >= threshold).any()]
    assert row["seeds_reaching_threshold"] == len(reaching)
    # the median over every seed, one that never reached the threshold later than any
    never = [np.inf] * (len(evals) - len(reaching))
    assert row["frames_to_threshold"] == np.median([*reaching, *never])
    summary = json.loads((whole / "summary.json").read_text())
    assert row["s_per_1000_with_eval"] == pytest.approx(1000 * summary["wall_s"] / (280 * c.seeds))
    fps = read_csv(whole / "seed_0" / "train.csv")["fps"]
    assert row["s_per_1000_training"] == pytest.approx(1000 / np.median(fps[np.isfinite(fps)]))
    acfg = experiment.agent_config(c, summary["action_dim"])
    assert row["params_m"] == pytest.approx(sum(report.param_counts(acfg).values()) / 1e6)
    assert "| dear " in text and (tmp_path / "table.md").read_text() == text
    assert read_csv(tmp_path / "table.csv")["final_return_mean"][0] == pytest.approx(finals.mean())
    assert row["eval_frame"] == row["eval_frame_min"] == 280 and row["task"] == "walker-walk"
    # --at: the evaluations up to a frame, for runs stopped at different points
    (early,) = report.run_rows(whole, threshold, at=150)
    assert early["eval_frame"] == 120
    firsts = np.array([e["episode_return"][e["frame"] <= 150][-1] for e in evals])
    assert early["final_return_mean"] == pytest.approx(firsts.mean())
    with pytest.raises(ValueError, match="at must be a frame >= 0, got -1"):
        report.run_rows(whole, threshold, at=-1)
    with pytest.raises(FileNotFoundError, match="config.json not found"):
        report.run_rows(tmp_path, threshold)


def test_the_runs_checkpointer_resumes_checkpoints_older_than_a_field(tmp_path):
    with contextlib.ExitStack() as stack:
        ckpt = train._checkpointer(tiny_config(), tmp_path, stack)
        assert ckpt.added_fields == experiment.ADDED_FIELDS
        assert ckpt.added_fields["env.distraction_types"] == "all"  # the suite before the field


def test_changed_learning_fields_are_refused_naming_them(run):
    workdir = run[0]
    changed = {"agent.batch_size": 2, "agent.alpha": 0.5, "total_frames": 400}
    with pytest.raises(IncompatibleCheckpointError) as err:
        train.train(tiny_config(**changed), workdir)
    message = str(err.value)
    assert "agent.batch_size: saved=4, now=2" in message
    assert "agent.alpha: saved=0.25, now=0.5" in message
    assert "total_frames" not in message  # may change: the fixture's resume changed it
    assert "env.backend" not in message
    with pytest.raises(IncompatibleCheckpointError) as err:  # the physics' old default
        train.train(tiny_config(**{"env.backend": "auto"}), workdir)
    assert "resumes with --config.env.backend=cpu" in str(err.value)


def test_fingerprint_is_every_field_but_the_resumable_ones():
    c = tiny_config()
    fp = experiment.fingerprint(c)
    assert {"agent.nstep", "agent.compute_dtype", "agent.ortho_form", "env.distraction"} <= set(fp)
    assert {"env.mask", "replay.capacity", "env.render.quality", "seed"} <= set(fp)
    assert not set(experiment.RESUMABLE_CHANGES) & set(fp)
    for key, value in experiment.ADDED_FIELDS.items():  # the defaults behave as before them
        assert fp[key] == value
    c.agent.new_field = 1  # a field added later counts, unless listed as resumable
    assert experiment.fingerprint(c)["agent.new_field"] == 1
    relaxed = tiny_config(
        total_frames=10,
        log_every_frames=7,
        eval_every_frames=9,
        checkpoint_every_frames=0,
        save_video=False,
        progress=True,
        **{"env.render.num_workers": 2},
    )
    assert experiment.fingerprint(relaxed) == experiment.fingerprint(tiny_config())


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--config.total_frames=-5"], "error: total_frames must be >= 1, got -5"),
        (
            ["--config.env.distraction=medium", "--config.env.background_dir=/nope"],
            "error: env.background_dir '/nope' is not a folder; give a DAVIS-2017 root",
        ),
    ],
)
def test_bad_input_says_one_line_and_leaves_nothing(tmp_path, flags, message):
    """A config the trainer refuses: run.py prints one line naming the problem (no traceback,
    no libraries' notes) and leaves no workdir behind."""
    workdir = tmp_path / "run"
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke", *flags, f"--workdir={workdir}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == [out.stderr.strip()]
    assert out.stderr.startswith(message) and not out.stdout
    assert not workdir.exists()


def test_a_file_given_as_workdir_is_refused_and_kept(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("mine")
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke", f"--workdir={path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    expected = f"error: --workdir {path} is a file: give a folder (a new one, or a run's)"
    assert (out.returncode, out.stderr.strip()) == (1, expected)
    assert path.read_text() == "mine"


@pytest.mark.parametrize(
    "flags, message",
    [
        (
            ["--config.replay.capacity=1000000000"],
            r"error: replay for 2 seeds x 1,000,000,000 entries",
        ),
        (["--config.agent.nstep=150"], r"error: agent.nstep=150 is longer than an episode"),
        (  # refused once its checkpoints/ and replay/ folders are made
            ["--config.total_frames=100000000000", "--config.checkpoint_every_frames=0"],
            r"error: the replay on disk \(.*\) may need [\d.]+ GiB more",
        ),
    ],
)
def test_input_the_run_finds_bad_says_one_line(tmp_path, flags, message):
    """What only the run can check (the replay against free memory or disk, an n-step return
    against the episode): one line naming the problem and its fix, exit status 2, no traceback;
    a new workdir is not left behind."""
    workdir = tmp_path / "run"
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke", *flags, f"--workdir={workdir}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert re.match(message, out.stderr.strip().splitlines()[-1])
    assert not workdir.exists()


def _smoke_run(workdir, **popen) -> subprocess.Popen:
    """run.py --config=smoke on `workdir`, started: its stdout and stderr piped, as text."""
    return subprocess.Popen(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke", f"--workdir={workdir}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,
    )


def _read_until(proc: subprocess.Popen, marker: str) -> list[str]:
    """The lines of `proc`'s stderr up to the first that holds `marker` (all, if none does)."""
    seen = []
    for line in proc.stderr:  # no terminal: a line per log interval instead of the bar
        seen.append(line)
        if marker in line:
            break
    return seen


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP])
def test_a_ctrl_c_while_the_run_starts_stops_it(tmp_path, sig):
    """SIGINT (or a closed terminal's SIGHUP) as soon as the run holds its workdir (during its
    imports, before training): it stops with 128 + the signal and one line, however early, and
    leaves no new workdir behind when it had not begun; a later one checkpoints first. Never
    does the run go on to train."""
    workdir = tmp_path / "run"
    # A terminal's dispositions, whatever this process's: a shell's background job (these tests
    # run as one) ignores SIGINT, and nohup SIGHUP, which its children inherit; a handler becomes
    # the default in a child at its exec.
    before = signal.signal(sig, signal.default_int_handler)
    try:
        # a process group of its own, as a terminal's foreground job
        proc = _smoke_run(workdir, start_new_session=True)
    finally:
        signal.signal(sig, before)
    deadline = time.time() + 120
    while not (workdir / "run.lock").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + sig and "Traceback" not in err
    last = err.strip().splitlines()[-1]
    if "before training began" in last:
        assert not workdir.exists()
    else:
        assert "checkpoint saved" in last


def test_a_stop_while_the_run_starts_saves_nothing(tmp_path, monkeypatch, capfd):
    """A signal while the run starts (here as its envs start) is acknowledged at once, and the
    run stops before its first step: no checkpoint, no summary; a resumed run's checkpoint
    stays the latest, named in the message."""
    from dear_jax import signals

    real = train.make_env

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # a handler runs between bytecodes
        return real(*args, **kwargs)

    workdir = tmp_path / "run"
    monkeypatch.setattr(train, "make_env", signalled)
    with pytest.raises(signals.StoppedBeforeTraining) as stopped:
        train.train(tiny_config(), workdir)
    assert str(stopped.value) == "stopped by SIGTERM before training began; nothing was saved"
    assert stopped.value.exit_code == 128 + signal.SIGTERM
    assert "SIGTERM received: stopping" in capfd.readouterr().err
    assert not list((workdir / "checkpoints").glob("*")) and not (workdir / "summary.json").exists()
    monkeypatch.setattr(train, "make_env", real)
    train.train(tiny_config(total_frames=120), workdir)
    saved = sorted(p.name for p in (workdir / "checkpoints").iterdir())
    monkeypatch.setattr(train, "make_env", signalled)
    with pytest.raises(signals.StoppedBeforeTraining) as stopped:
        train.train(tiny_config(), workdir)
    assert str(stopped.value).endswith("nothing was saved (the checkpoint at frame 120 stays)")
    assert sorted(p.name for p in (workdir / "checkpoints").iterdir()) == saved


def test_a_sigterm_as_the_run_starts_its_envs_removes_its_new_workdir(tmp_path):
    """run.py sent SIGTERM once its envs have started (its log says where it evaluates), before
    its first update: 143, the signal acknowledged at once, and, stopped before training, no
    new workdir left behind (a stop that lands after the first step checkpoints instead)."""
    workdir = tmp_path / "run"
    proc = _smoke_run(workdir)
    seen = _read_until(proc, "evaluations: ")  # logged once the envs have started
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    err = "".join(seen) + err
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "SIGTERM received: stopping" in err
    last = err.strip().splitlines()[-1]
    if "before training began" in last:
        assert last == "stopped by SIGTERM before training began; nothing was saved"
        assert not workdir.exists()
    else:
        assert "checkpoint saved" in last


def test_two_sigterms_as_the_run_starts_leave_no_new_workdir(tmp_path):
    """Two SIGTERMs 1.2 s apart once run.py's envs have started: the second may land while the
    first's stop before training unwinds (its evaluation process closing). Stopped at once with
    nothing saved or logged, the new workdir goes as after one signal; one that had logged
    training keeps it."""
    workdir = tmp_path / "run"
    proc = _smoke_run(workdir)
    seen = _read_until(proc, "evaluations: ")
    proc.send_signal(signal.SIGTERM)
    time.sleep(1.2)  # past the first's repeats (signals.REPEAT_WINDOW_S): a second request
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    err = "".join(seen) + err
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    if "checkpoint saved" not in err:
        assert workdir.exists() == any(workdir.glob("*/*.csv")), err[-2000:]


def test_a_second_signal_stops_at_once_and_sighup_asks_for_a_stop():
    """The first SIGTERM asks for a stop at the end of the step; its repeat at once (`timeout`
    signals the process, then its process group) is the same request; a second one later stops
    at once with StoppedAtOnce, a KeyboardInterrupt that names the signal (run.py: one line,
    128 + signal)."""
    from dear_jax import signals

    with signals.StopRequest() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # a handler runs between bytecodes
        assert stop.signum == signal.SIGTERM
        os.kill(os.getpid(), signal.SIGTERM)  # as the process group's copy
        time.sleep(0.05)
        assert stop.signum == signal.SIGTERM  # no StoppedAtOnce: the first's repeat
        time.sleep(signals.REPEAT_WINDOW_S)
        with pytest.raises(signals.StoppedAtOnce) as raised:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
    assert raised.value.signum == signal.SIGTERM and isinstance(raised.value, KeyboardInterrupt)
    assert str(raised.value) == "a second SIGTERM: stopped at once"
    # A closed terminal's SIGHUP asks for a stop too, unless the process ignores it (nohup: as
    # these tests may run themselves, whose SIGHUP is set here both ways).
    before = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        with signals.StopRequest() as stop:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(0.05)
            assert stop.signum == signal.SIGHUP and stop.name == "SIGHUP"
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        with signals.StopRequest() as stop:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(0.05)
            assert not stop and signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)


def test_config_by_bare_name_and_unknown_names():
    """`--config walker_dear.py` (or `smoke`) is looked up in configs/; an unknown name lists them."""
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config", "smoke", "--config.agent.alpah=1"],
        cwd=ROOT / "tests",  # not the repo root: the name is looked up next to run.py
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0
    assert "Did you mean 'agent.alpha'" in out.stderr and "batch_size" in out.stderr
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke", "--config.seeds=two"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (out.returncode, out.stderr.strip()) == (
        1,
        "error: --config.seeds=two: seeds takes an integer (the config's: 2), not 'two'",
    )
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=walker_dear.pyy"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0
    assert (
        "Did you mean 'walker_dear.py'" in out.stderr and "walker_dear_beta_sweep.py" in out.stderr
    )
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config=smoke.py:walker"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert "smoke.py takes no config string after ':' (paper.py does" in out.stderr
    configs = ROOT / "configs"
    assert resolve_config_path("walker_dear.py", configs) == configs / "walker_dear.py"
    assert resolve_config_path("walker_dear", configs) == configs / "walker_dear.py"
    assert resolve_config_path(str(configs / "smoke.py"), configs) == configs / "smoke.py"
    # Files of settings other configs build on are not offered, and refuse to be a run's.
    with pytest.raises(FileNotFoundError) as err:
        resolve_config_path("kitchn", configs)
    assert "paper.py" in str(err.value) and "kitchen.py" not in str(err.value)
    with pytest.raises(ValueError, match="paper.py:light,METHOD"):
        load_config("kitchen")


def test_every_experiment_of_the_paper_has_a_config():
    """configs/paper.py's grid (tasks x methods x difficulties, mask variants) and the weight
    ablations load and pass the trainer's checks; bad config strings name the valid choices."""
    import itertools

    from configs import paper, walker_dear_beta_sweep, walker_dear_loss_ablation
    from dear_jax import lanes

    grid = itertools.product(("walker", "cup", "finger"), paper.METHODS, paper.DIFFICULTIES)
    for task, method, difficulty in grid:
        c = paper.get_config(f"{task},{method},{difficulty}")
        experiment.validate(c)
        level = difficulty.removesuffix("-full")
        assert (c.agent.method, c.env.distraction) == (method, level)
        # The paper's setting: background videos only; "-full": the whole suite.
        full = difficulty.endswith("-full")
        if level != "none":
            assert c.env.distraction_types == ("all" if full else "background")
    for mask in paper.MASKS:
        assert paper.get_config(f"walker,dear,medium,{mask}").env.mask == mask
    assert paper.get_config("kettle,sear").env.task == "kitchen-kettle"
    sweep = walker_dear_beta_sweep.get_config()
    assert [lane.settings for lane in lanes.lanes(sweep)][::3] == [
        (("beta", b),) for b in (-1, 0, 1, 10, 100)
    ]
    assert len(lanes.lanes(walker_dear_loss_ablation.get_config())) == 12
    with pytest.raises(ValueError, match="unknown difficulty 'extreme'.*none, easy, medium, hard"):
        paper.get_config("walker,dear,extreme")
    with pytest.raises(ValueError, match="unknown difficulty 'medium-fll'.*, medium-full, "):
        paper.get_config("walker,dear,medium-fll")
    out = subprocess.run(
        [sys.executable, str(ROOT / "run.py"), "--config", "paper.py:walker,dreamer"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0 and "valid: drqv2, dear, sear, ted" in out.stderr


def test_bad_values_fail_with_valid_choices(tmp_path):
    with pytest.raises(ValueError, match="valid: .*walker-walk"):
        train.train(tiny_config(**{"env.task": "walker-jump"}), tmp_path)
    with pytest.raises(ValueError, match="valid: drqv2, dear, sear, ted"):
        train.train(tiny_config(**{"agent.method": "dreamer"}), tmp_path)
    with pytest.raises(FileNotFoundError, match="DAVIS-2017"):
        train.train(tiny_config(**{"env.background_dir": str(tmp_path / "nope")}), tmp_path)
    with pytest.raises(MemoryError, match="replay for 2 seeds"):
        train.train(tiny_config(**{"replay.capacity": 10**9}), tmp_path)
    with pytest.raises(ValueError, match="agent.shift_impl 'roll'; valid: pad_slice, gather"):
        train.train(tiny_config(**{"agent.shift_impl": "roll"}), tmp_path)
    with pytest.raises(ValueError, match="eval_device 'gpu'; valid: auto, cpu, accelerator, train"):
        train.train(tiny_config(eval_device="gpu"), tmp_path)
    with pytest.raises(
        ValueError,
        match="distraction_types: unknown 'sky' in distraction types 'sky': give one or more of ",
    ):
        train.train(tiny_config(**{"env.distraction_types": "sky"}), tmp_path)
    with pytest.raises(ValueError, match="env.eval_physics_threads must be >= 0.*got -1"):
        train.train(tiny_config(**{"env.eval_physics_threads": -1}), tmp_path)
    with pytest.raises(ValueError, match=r"env.physics_threads must be >= 0 \(0: one per device"):
        train.train(tiny_config(**{"env.physics_threads": -2}), tmp_path)
    with pytest.raises(ValueError, match=r"env.switch_interval_ms must be >= 0 \(0: Python's own"):
        train.train(tiny_config(**{"env.switch_interval_ms": -1.0}), tmp_path)


def test_the_loop_runs_at_the_configured_switch_interval(run, tmp_path, monkeypatch):
    """env.switch_interval_ms is Python's thread switch interval while the loop steps; the
    caller's comes back after the run; 0 leaves the caller's."""
    seen = []
    step = loop.Loop.step
    monkeypatch.setattr(
        loop.Loop, "step", lambda self, p: (seen.append(sys.getswitchinterval()), step(self, p))
    )
    before = sys.getswitchinterval()
    train.train(tiny_config(total_frames=40, **{"env.switch_interval_ms": 0.25}), tmp_path)
    assert seen and all(s == pytest.approx(0.25e-3) for s in seen)
    assert sys.getswitchinterval() == before
    with train.switch_interval(0.0):
        assert sys.getswitchinterval() == before


def test_envs_step_their_physics_on_the_configured_threads():
    """env.eval_physics_threads reaches the evaluation env's CPU physics; 0 is one thread per
    core this process may use, up to 8. env.physics_threads reaches any training env made from
    the config (the loop's and the benchmarks'); 0 is one per device, here one."""
    cores = min(8, len(os.sched_getaffinity(0)))
    for setting, threads in ((3, 3), (0, cores)):
        env = experiment.make_eval_env(tiny_config(**{"env.eval_physics_threads": setting}))
        try:
            assert env.physics.threads == threads
            assert env.shape[1] == tiny_config().num_eval_episodes
        finally:
            env.close()
    for setting, threads in ((3, 3), (0, 1)):
        config = tiny_config(**{"env.physics_threads": setting})
        env = experiment.make_env(config, envs_per_seed=2, split="train", seed=0)
        try:
            assert env.physics.threads == threads
        finally:
            env.close()


def test_every_evaluation_process_shows_the_runs_builtin_videos():
    """Without DAVIS, the built-in background videos follow the run's seed, not an env's: the
    evaluation processes (streams) of a run composite one validation set, though each draws
    its own episodes; another run seed has other videos."""
    config = tiny_config(**{"env.distraction": "medium", "env.distraction_types": "background"})
    made = [experiment.make_eval_env(config, stream=s) for s in (0, 1)]
    config.seed = 1
    made.append(experiment.make_eval_env(config))
    try:
        first, second, other = (np.asarray(env._backgrounds) for env in made)
        assert first.shape[0] == 8  # medium: 8 videos
        np.testing.assert_array_equal(first, second)
        assert not np.array_equal(first, other)
        (_, a), (_, b) = (env.reset(jax.random.key(0)) for env in made[:2])
        assert not np.array_equal(np.asarray(a.frame), np.asarray(b.frame))
    finally:
        for env in made:
            env.close()


def test_benchmarks_set_any_config_field_typed_and_by_known_name():
    """`--set KEY=VALUE` of benchmarks/train.py (and profile_loop.py): typed as the field is,
    unknown keys refused with the valid fields."""
    from benchmarks.train import set_field

    config = tiny_config()
    set_field(config, "agent.shift_impl=one_hot")
    set_field(config, "agent.batch_size=64")
    set_field(config, "replay.disk=false")
    assert (config.agent.shift_impl, config.agent.batch_size, config.replay.disk) == (
        "one_hot",
        64,
        False,
    )
    with pytest.raises(KeyError, match="Did you mean 'agent.shift_impl'"):
        set_field(config, "agent.shift=gather")
    with pytest.raises(ValueError, match="KEY=VALUE"):
        set_field(config, "agent.shift_impl")
    with pytest.raises(ValueError, match="invalid literal"):
        set_field(config, "agent.batch_size=big")


def test_override_values_a_field_cannot_take_are_refused_naming_its_type():
    """`--config.KEY=VALUE` checked as ml_collections will parse it (absl's parsers), before
    absl's own two-line error: a bool, int or float field refuses what it cannot take, naming
    what it takes; a string field takes anything, and so does a field declared of type object
    whatever its value (devices: 1 or "all"); an unknown key stays a KeyError."""
    from dear_jax.config import check_override_keys

    config = tiny_config()
    fine = [
        "--config.progress=false",
        "--config.progress=True",
        "--config.seeds=3",
        "--config.total_frames=2_000",
        "--config.agent.lr=1e-4",
        "--config.agent.lr=3",
        "--config.agent.method=anything",
        "--config.devices=all",
        "--config.devices=2",
        "--config.seeds",  # a value in the next word: absl's to parse
    ]
    check_override_keys(config, fine)
    for arg, message in [
        ("--config.progress=maybe", "progress takes true or false (the config's: False)"),
        ("--config.seeds=1.5", "seeds takes an integer (the config's: 2), not '1.5'"),
        ("--config.agent.lr=fast", "agent.lr takes a number (the config's: 0.0001), not 'fast'"),
    ]:
        with pytest.raises(ValueError, match=re.escape(f"{arg}: {message}")):
            check_override_keys(config, [arg])
    with pytest.raises(KeyError, match="unknown config key 'agent.lrr'"):
        check_override_keys(config, ["--config.agent.lrr=1"])


def test_benchmarks_vary_fields_over_every_combination():
    """`--vary KEY V1 V2` of benchmarks/train.py: every combination, the last key fastest."""
    from benchmarks.train import variants

    assert variants(
        [["env.physics_threads", "1", "4"], ["env.switch_interval_ms", "0", "0.1"]]
    ) == [
        ["env.physics_threads=1", "env.switch_interval_ms=0"],
        ["env.physics_threads=1", "env.switch_interval_ms=0.1"],
        ["env.physics_threads=4", "env.switch_interval_ms=0"],
        ["env.physics_threads=4", "env.switch_interval_ms=0.1"],
    ]
    assert variants([["agent.kernels", "", "BLOCK=64,NUM_WARPS=4"]]) == [
        ["agent.kernels="],
        ["agent.kernels=BLOCK=64,NUM_WARPS=4"],
    ]
    with pytest.raises(ValueError, match="--vary takes a KEY and its values"):
        variants([["env.physics_threads"]])


def test_benchmarks_draw_on_the_gpus_that_train_unless_told(monkeypatch):
    """benchmarks/train.py's figures do not depend on a machine's spare GPUs: "auto" becomes
    the GPUs of the run's lanes where the process sees more; settings given stay."""
    from types import SimpleNamespace

    from benchmarks.train import drawn_beside_lanes

    gpus = [SimpleNamespace(platform="gpu", local_hardware_id=i) for i in range(3)]
    monkeypatch.setattr(jax, "local_devices", lambda: gpus)
    monkeypatch.delenv("MUJOCO_EGL_DEVICE_ID", raising=False)
    config = smoke.get_config()
    for devices, drawn in [(1, "0"), (2, "0,1"), (3, "auto"), ("all", "auto")]:
        config.devices = devices
        assert drawn_beside_lanes(config).env.render.gpus == drawn
    assert config.env.render.gpus == "auto"  # a copy was changed, not the config given
    config.devices = 1
    config.env.render.gpus = "2"
    assert drawn_beside_lanes(config).env.render.gpus == "2"
    config.env.render.gpus = "auto"
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "1")
    assert drawn_beside_lanes(config).env.render.gpus == "auto"


def test_the_train_benchmark_can_leave_out_the_label_pass(monkeypatch):
    """benchmarks/train.py --label-pass off: the training loop's env is made without the
    segmentation pass (a DEAR config draws it otherwise); "auto" leaves make_env as it is."""
    from benchmarks import train as bench
    from dear_jax import experiment, train

    drawn = []
    monkeypatch.setattr(
        experiment.envs, "make", lambda *a, render, **k: drawn.append(render.labels)
    )
    config = smoke.get_config()
    assert config.agent.method == "dear"
    for setting in ("off", "auto"):
        with bench.label_pass(setting):
            train.make_env(config, envs_per_seed=1, split="train", seed=0)
    assert drawn == [False, True]
    assert train.make_env is experiment.make_env


def test_benchmarks_vary_stops_at_a_signal(tmp_path, monkeypatch, capsys):
    """A setting cut short by a signal (a time limit's SIGTERM) keeps its rows, and the settings
    after it are not started: the command ends instead of measuring on past its limit."""
    import sys

    from benchmarks import train as bench

    measured = []

    def throughput(config, warmup_frames, labels):  # the second setting is stopped
        assert labels == "auto"
        measured.append(config.env.physics_threads)
        return {"aggregate_fps": 1.0, "updates_per_seed": None if len(measured) == 2 else 5}

    monkeypatch.setattr(bench, "throughput", throughput)
    out = tmp_path / "vary.json"
    argv = ["train.py", "--config", "configs/smoke.py", "--skip", "split", "--out", str(out)]
    argv += ["--vary", "env.physics_threads", "1", "2", "3", "--rounds", "2"]
    monkeypatch.setattr(sys, "argv", argv)
    bench.main()
    assert measured == [1, 2]
    saved = json.loads(out.read_text())["variants"]
    assert [v["set"] for v in saved] == [["env.physics_threads=1"], ["env.physics_threads=2"]]
    assert "stopped: 4 setting(s) not measured" in capsys.readouterr().out


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            {"replay.seed_frames": 0},
            r"seed_frames=0 gives 0 transitions .* set replay.seed_frames >= 8",
        ),
        ({"replay.seed_frames": 6}, r"fewer than one batch \(agent.batch_size=4\)"),
        (
            {"replay.capacity": 4, "agent.batch_size": 8, "replay.seed_frames": 16},
            r"larger than the replay",
        ),
        (
            {"agent.nstep": 21},
            r"agent.nstep=21 is longer than an episode of walker-walk \(20 agent steps\)",
        ),
        (
            {"agent.latent_dim": 255},
            r"agent.latent_dim=255 must be even: the latent splits into halves",
        ),
        (
            {"agent.kernels": "BLOK=64"},
            r"agent.kernels: kernel constant 'BLOK=64': give NAME=INT with NAME one of BLOCK, ",
        ),
    ],
)
def test_configs_that_cannot_work_are_refused_by_name(overrides, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        train.train(tiny_config(**overrides), tmp_path)
    assert not (tmp_path / "checkpoints").exists()  # refused before anything was allocated


def test_a_run_too_short_to_update_says_so(caplog):
    """A run that ends before its first update (a check of the envs and evaluations, or a slip)
    is told so when it starts; one that updates is not."""
    with caplog.at_level(logging.WARNING, logger="dear_jax"):
        experiment.validate(tiny_config(total_frames=120))
        experiment.validate(tiny_config(total_frames=160))
    (warning,) = [r.getMessage() for r in caplog.records if "seed_frames" in r.getMessage()]
    assert warning.startswith("replay.seed_frames=120 is not below total_frames=120: this run ")


def test_kernel_constants_with_the_xla_stack_are_named_as_doing_nothing(caplog):
    """agent.kernels sets the Pallas stacks' constants: with XLA's convolutions (this CPU
    machine's "auto") the run is told it changes nothing; set, they are accepted."""
    with caplog.at_level("WARNING", logger="dear_jax"):
        experiment.validate(tiny_config(**{"agent.kernels": "BLOCK=64"}))
    assert "agent.kernels='BLOCK=64' sets the Pallas stacks' constants" in caplog.text
    assert "agent.conv_stack='auto'): it changes nothing" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="dear_jax"):
        experiment.validate(
            tiny_config(**{"agent.kernels": "BLOCK=64", "agent.conv_stack": "pallas"})
        )
    assert "agent.kernels" not in caplog.text


def _overrides(config) -> list[str]:
    """--config.key=value arguments that make configs/smoke.py into `config`."""
    base = lanes.flatten(smoke.get_config().to_dict())
    want = lanes.flatten(config.to_dict())
    return [f"--config.{k}={v}" for k, v in want.items() if base.get(k) != v]


def _descendants(pid: int) -> list[int]:
    """Every process below `pid` (render workers are children of multiprocessing's fork server)."""
    parents = {}
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        try:
            parents[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
    found, frontier = [], [pid]
    while frontier:
        below = [p for p, parent in parents.items() if parent in frontier]
        found += below
        frontier = below
    return found


def test_sigterm_checkpoints_exits_cleanly_and_resumes_exactly(run, tmp_path):
    """run.py sent SIGTERM mid-run saves a checkpoint and exits with 143, leaving no shared
    memory and no render worker behind; meanwhile a second run on its workdir is refused; resumed,
    the run ends exactly as the uninterrupted one (the fixture's, drawn by 1 render worker per
    env where this run has 2)."""
    workdir = tmp_path / "w"
    config = tiny_config(total_frames=280, **{"env.render.num_workers": 2})
    cmd = [sys.executable, "run.py", "--config", "smoke", f"--workdir={workdir}"]
    cmd += _overrides(config)
    env = dict(os.environ, MUJOCO_GL="egl", JAX_PLATFORMS="cpu")
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    seen = _read_until(proc, "eval @ 120 frames")  # one line per evaluation
    workers = _descendants(proc.pid)
    second = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=300)
    err = "".join(seen) + err
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert second.returncode != 0 and f"in use by pid {proc.pid}" in second.stderr
    assert "stopped by SIGTERM" in err and "rerun the same command" in err
    for noise in ("leaked", "Traceback", "Failed to import", "orbax", "absl"):
        assert noise not in out + err, noise
    assert len(err.splitlines()) < 15, err  # a quiet console: a few lines per run
    deadline = time.monotonic() + 30
    while any(pathlib.Path(f"/proc/{p}").exists() for p in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(workers) >= 4  # render workers of both envs, the fork server, the tracker
    assert not [p for p in workers if pathlib.Path(f"/proc/{p}").exists()]
    assert not (workdir / "run.lock").exists()
    assert "stopped by SIGTERM" in (workdir / "log.txt").read_text()
    stopped_at = Checkpointer(workdir / "checkpoints", fingerprint={}).latest_step()
    assert 120 <= stopped_at < 280
    summary = json.loads((workdir / "summary.json").read_text())  # of the run so far
    assert summary["stopped"] == "SIGTERM" and summary["frames_per_seed"] == stopped_at
    assert "stopped by SIGTERM at" in (workdir / "summary.md").read_text()
    (row,) = report.run_rows(workdir, threshold=0.0)  # Table II reads it, marked as stopped
    assert row["run"].endswith(f"(stopped at {stopped_at:,} frames)")
    train.train(config, workdir)  # resumes in this process
    assert_same_run(run[-1], workdir, 280)


def test_stale_lock_is_taken_over(tmp_path, caplog):
    from dear_jax.lock import WorkdirLock, WorkdirLocked

    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True
    )
    (tmp_path / "run.lock").write_text(
        json.dumps({"pid": int(dead.stdout), "host": socket.gethostname(), "since": "earlier"})
    )
    with WorkdirLock(tmp_path):
        assert json.loads((tmp_path / "run.lock").read_text())["pid"] == os.getpid()
        assert "no longer running" in caplog.text
    assert not (tmp_path / "run.lock").exists()
    (tmp_path / "run.lock").write_text(json.dumps({"pid": 1, "host": "elsewhere"}))
    with pytest.raises(WorkdirLocked, match="delete .*run.lock"):
        WorkdirLock(tmp_path).acquire()
    # Two runs taking over one stale lock at once: the slower finds the faster's fresh lock in
    # its place and leaves it there (not deleted, as a read-then-delete would).
    stale, fresh = {"pid": 2, "host": "h"}, {"pid": 3, "host": "h"}
    (tmp_path / "run.lock").write_text(json.dumps(fresh))
    WorkdirLock(tmp_path)._remove_stale(stale, tmp_path / "aside")
    assert json.loads((tmp_path / "run.lock").read_text()) == fresh
    WorkdirLock(tmp_path)._remove_stale(fresh, tmp_path / "aside")
    assert not (tmp_path / "run.lock").exists() and not (tmp_path / "aside").exists()


# Last in this file: its two-lane programs replace the fixture's in the trainer's program cache
# (one experiment per process, programs.cached_programs), which the tests above reuse (the resume of
# test_sigterm_checkpoints_exits_cleanly_and_resumes_exactly would compile them again).
def test_a_sweep_trains_each_lane_with_its_own_settings(tmp_path):
    """`sweep.beta = "0,100"` with one seed: two lanes in one program, each logging under its
    settings' name with its own config.json; every logged loss is L_critic + alpha L_mask +
    beta L_dis with its lane's beta; the summary and Table II have a row per setting."""
    c = tiny_config(seeds=1, total_frames=160)
    c.sweep.beta = "0,100"
    summary = train.train(c, tmp_path)
    assert [p["lane"] for p in summary["per_seed"]] == ["beta=0_seed_0", "beta=100_seed_0"]
    assert summary["lanes"] == 2 and summary["sweep"] == {"beta": [0.0, 100.0]}
    for beta in (0, 100):
        lane = tmp_path / f"beta={beta}_seed_0"
        config = json.loads((lane / "config.json").read_text())
        assert config["agent"]["beta"] == beta and config["lane"]["settings"] == {"beta": beta}
        log = read_csv(lane / "train.csv")
        rows = np.isfinite(log["loss"])
        assert rows.sum() >= 1 and np.all(log["ortho_loss"][rows] > 0)
        want = log["critic_loss"] + c.agent.alpha * log["mask_loss"] + beta * log["ortho_loss"]
        np.testing.assert_allclose(log["loss"][rows], want[rows], rtol=1e-4)
        assert (lane / "eval.csv").is_file() and (lane / "tb").is_dir()
    assert sorted(p.name for p in (tmp_path / "videos").iterdir())[0].endswith("_seed_0.mp4")
    rows, _ = report.runs_table([tmp_path], threshold=1.0)
    assert [r["run"] for r in rows] == [f"{tmp_path.name} beta=0", f"{tmp_path.name} beta=100"]
