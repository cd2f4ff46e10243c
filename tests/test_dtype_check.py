"""benchmarks/dtype_check.py: the fp32-vs-bf16 learning check, on hand-made logs."""

import csv
import json

import numpy as np
import pytest

from benchmarks import dtype_check


def _write(path, header, rows):
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def _run(root, name, returns_per_seed, frames=(0, 10, 20, 30), loss=0.0, seeds=None):
    """Seed s logs eval returns at `frames` and a critic loss of loss + s + frame / 100 five
    frames after each evaluation but the first."""
    run = root / name
    for s, returns in zip(seeds or range(len(returns_per_seed)), returns_per_seed):
        d = run / f"seed_{s}"
        d.mkdir(parents=True)
        _write(d / "eval.csv", ["frame", "episode_return"], zip(frames, returns))
        train = [(f + 5, loss + s + (f + 5) / 100) for f in frames[1:]]
        _write(d / "train.csv", ["frame", "critic_loss"], train)
    return run


def test_paired_comparison_over_common_evaluations(tmp_path):
    # Run A has one evaluation more (frame 40): only frames 10, 20, 30 are compared.
    a = _run(tmp_path, "a", [[0, 10, 20, 30, 99], [0, 30, 40, 50, 99]], (0, 10, 20, 30, 40))
    b = _run(tmp_path, "b", [[0, 12, 22, 32], [0, 26, 36, 46]], loss=1.0)
    r = dtype_check.compare(a, b)
    assert r["frames"] == [10, 20, 30]
    assert r["mean_return_per_seed"] == {"a": [20.0, 40.0], "b": [22.0, 36.0]}
    assert r["paired_difference"] == [2.0, -4.0] and r["mean_difference"] == -1.0
    assert r["seed_spread_b"] == pytest.approx(np.std([22.0, 36.0], ddof=1))
    # paired t over d = (2, -4): mean -1, sd sqrt(18), t = -1 / (sqrt(18) / sqrt(2)) = -1/3,
    # one degree of freedom: p = 1 - 2 atan(1/3) / pi
    assert r["t_statistic"] == pytest.approx(-1 / 3)
    assert r["p_value"] == pytest.approx(1 - 2 * np.arctan(1 / 3) / np.pi)
    assert r["within_noise"]
    # losses at the last train frame both runs logged (35; A also has 45)
    assert r["train_frame"] == 35
    assert r["train_losses"]["a"]["critic_loss"] == pytest.approx([0.35, 1.35])
    assert r["train_losses"]["b"]["critic_loss"] == pytest.approx([1.35, 2.35])
    assert "within noise: yes" in dtype_check.report(r)
    out = tmp_path / "check.json"
    assert dtype_check.main([str(a), str(b), "--out", str(out)]) == r
    assert json.loads(out.read_text())["paired_difference"] == [2.0, -4.0]
    # --upto: the evaluations up to frame 20, the losses of the last log up to it (25 > 20)
    r = dtype_check.compare(a, b, upto=20)
    assert r["frames"] == [10, 20] and r["train_frame"] == 15


def test_identical_runs_are_noise_and_a_clear_gap_is_not(tmp_path):
    a = _run(tmp_path, "a", [[0, 10, 10, 10], [0, 12, 12, 12], [0, 11, 11, 11]])
    same = dtype_check.compare(a, a)
    assert same["paired_difference"] == [0.0, 0.0, 0.0] and same["p_value"] == 1.0
    assert same["within_noise"]
    b = _run(tmp_path, "b", [[0, 110, 110, 110], [0, 112, 112, 111], [0, 111, 111, 111]])
    assert not dtype_check.compare(a, b)["within_noise"]


def test_bad_input_is_named(tmp_path):
    a = _run(tmp_path, "a", [[0, 1, 2, 3]] * 3)
    with pytest.raises(FileNotFoundError, match="no seed_"):
        dtype_check.compare(a, tmp_path / "nowhere")
    other = _run(tmp_path, "other", [[0, 1, 2, 3]] * 3, seeds=[0, 2, 3])
    with pytest.raises(ValueError, match="different seeds"):
        dtype_check.compare(a, other)
    with pytest.raises(ValueError, match="eval.csv have no common frame after 0 up to 5 frames"):
        dtype_check.compare(a, a, upto=5)
