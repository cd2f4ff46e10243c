"""The trainer end to end on CPU: outputs, resume, seeds, and clear errors for bad input."""

import json
import pathlib
import subprocess
import sys

import cv2
import numpy as np
import pytest

from configs import smoke
from dear_jax import train
from dear_jax.checkpoint import Checkpointer, IncompatibleCheckpointError
from dear_jax.logger import read_csv

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
    c.agent.batch_size = 8
    c.agent.latent_dim = 64
    c.agent.hidden_dim = 32
    c.agent.feature_dim = 8
    c.agent.explore_steps = 40
    c.replay.seed_frames = 120
    c.replay.capacity = 1000
    for key, value in overrides.items():
        node = c
        *parents, leaf = key.split(".")
        for part in parents:
            node = node[part]
        node[leaf] = value
    return c


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One run to 200 frames per seed, then the same workdir resumed to 280.

    The replay goes into the checkpoints, so the resumed run updates from its first step.
    """
    workdir = tmp_path_factory.mktemp("run")
    first = train.train(tiny_config(save_replay=True), workdir)
    saved_step = Checkpointer(workdir / "checkpoints", fingerprint={}).latest_step()
    resumed = train.train(tiny_config(total_frames=280, save_replay=True), workdir)
    return workdir, first, resumed, saved_step


def test_outputs_exist_and_parse(run):
    workdir, first, _, _ = run
    config = json.loads((workdir / "config.json").read_text())
    assert config["agent"]["method"] == "dear" and config["seeds"] == 2
    for seed in (0, 1):
        train_log = read_csv(workdir / f"seed_{seed}" / "train.csv")
        assert {"frame", "critic_loss", "mask_loss", "ortho_loss", "fps"} <= set(train_log)
        assert np.all(np.isfinite(train_log["frame"]))
        eval_log = read_csv(workdir / f"seed_{seed}" / "eval.csv")
        assert {"episode_return", "cos_agent_env", "fps", "sec_per_1000_frames"} <= set(eval_log)
        assert list(eval_log["frame"][:3]) == [0, 120, 200]  # frame 0: the untrained policy
        assert any((workdir / f"seed_{seed}" / "tb").iterdir())
    video = workdir / "videos" / "eval_200_seed0.mp4"
    cap = cv2.VideoCapture(str(video))
    ok, frame = cap.read()
    assert ok and frame.shape[1] >= 3 * frame.shape[0]  # RGB | true mask | predicted mask
    assert (workdir / "summary.md").read_text().startswith("# dear on walker-walk")
    summary = json.loads((workdir / "summary.json").read_text())  # rewritten by the resume
    assert summary["frames_per_seed"] == 280 and len(summary["per_seed"]) == 2
    assert first["frames_per_seed"] == 200


def test_frames_and_updates_follow_the_papers_ratio(run):
    """Frames count per seed over its E envs; one update per 2 agent steps after seed frames."""
    workdir, first, resumed, _ = run
    c = tiny_config()
    frames_per_step = c.envs_per_seed * c.env.action_repeat  # one loop iteration, per seed
    steps_learned = (200 - c.replay.seed_frames) // frames_per_step * c.envs_per_seed
    assert first["updates_per_seed"] == steps_learned // c.agent.update_every_steps
    resumed_steps = (280 - 200) // frames_per_step * c.envs_per_seed
    assert resumed["updates_per_seed"] == (
        first["updates_per_seed"] + resumed_steps // c.agent.update_every_steps
    )
    # An episode of episode_frames per env is E x episode_frames frames of its seed (checked up
    # to the resume, which starts new episodes).
    log = read_csv(workdir / "seed_0" / "train.csv")
    before = log["frame"] <= 200
    assert before.sum() >= 3
    episode = c.env.episode_frames * c.envs_per_seed
    np.testing.assert_array_equal(log["episode"][before], log["frame"][before] // episode)


def test_resume_continues_from_saved_step(run):
    workdir, first, resumed, saved_step = run
    assert saved_step == 200
    assert resumed["frames_per_seed"] == 280
    frames = read_csv(workdir / "seed_0" / "eval.csv")["frame"]
    assert list(frames) == [0, 120, 200, 240, 280]  # no frame evaluated twice, none lost
    assert (
        sorted(p.name for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())[-1] == "280"
    )


def test_seeds_differ(run):
    workdir = run[0]
    a = read_csv(workdir / "seed_0" / "train.csv")
    b = read_csv(workdir / "seed_1" / "train.csv")
    assert not np.allclose(a["critic_loss"], b["critic_loss"], equal_nan=True)


def test_same_config_reproduces_the_first_updates(tmp_path):
    c = tiny_config(total_frames=160, eval_every_frames=10**6, save_video=False)
    results = []
    for name in ("a", "b"):
        train.train(c, tmp_path / name)
        results.append(read_csv(tmp_path / name / "seed_0" / "train.csv")["critic_loss"])
    np.testing.assert_array_equal(results[0], results[1])


def test_incompatible_checkpoint_is_refused(run, tmp_path):
    workdir = run[0]
    with pytest.raises(IncompatibleCheckpointError, match="agent.method"):
        train.train(tiny_config(**{"agent.method": "drqv2", "total_frames": 400}), workdir)


def test_unknown_config_key_fails_with_valid_choices():
    out = subprocess.run(
        [sys.executable, "run.py", "--config", "configs/smoke.py", "--config.agent.alpah=1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode != 0
    assert "Did you mean 'agent.alpha'" in out.stderr and "batch_size" in out.stderr


def test_bad_values_fail_with_valid_choices(tmp_path):
    with pytest.raises(ValueError, match="valid: .*walker-walk"):
        train.train(tiny_config(**{"env.task": "walker-jump"}), tmp_path)
    with pytest.raises(ValueError, match="valid: drqv2, dear, sear, ted"):
        train.train(tiny_config(**{"agent.method": "dreamer"}), tmp_path)
    with pytest.raises(FileNotFoundError, match="DAVIS-2017"):
        train.train(tiny_config(**{"env.background_dir": str(tmp_path / "nope")}), tmp_path)
    with pytest.raises(MemoryError, match="replay for 2 seeds"):
        train.train(tiny_config(**{"replay.capacity": 10**9}), tmp_path)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            {"replay.seed_frames": 0},
            r"seed_frames=0 gives 0 transitions .* set replay.seed_frames >= 16",
        ),
        ({"replay.seed_frames": 14}, r"fewer than one batch \(agent.batch_size=8\)"),
        (
            {"replay.capacity": 4, "agent.batch_size": 8, "replay.seed_frames": 16},
            r"larger than the replay",
        ),
        (
            {"agent.nstep": 21},
            r"agent.nstep=21 is longer than an episode of walker-walk \(20 agent steps\)",
        ),
    ],
)
def test_configs_that_cannot_work_are_refused_by_name(overrides, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        train.train(tiny_config(**overrides), tmp_path)
    assert not (tmp_path / "checkpoints").exists()  # refused before anything was allocated
