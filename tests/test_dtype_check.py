"""benchmarks/dtype_check.py: the fp32-vs-bf16 learning check, on hand-made logs."""

import csv

import numpy as np
import pytest

from benchmarks import dtype_check


def _run(root, name, returns_per_seed, frames=(0, 10, 20, 30)):
    run = root / name
    for s, returns in enumerate(returns_per_seed):
        d = run / f"seed_{s}"
        d.mkdir(parents=True)
        with (d / "eval.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame", "episode_return"])
            w.writerows(zip(frames, returns))
        with (d / "train.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame", "critic_loss"])
            w.writerows([(5, 1.0 + s), (frames[-1] + 5, 2.0 + s)])
    return run


def test_paired_comparison_over_common_evaluations(tmp_path):
    # fp32 has one evaluation more (frame 40): only frames 10, 20, 30 are compared.
    fp32 = _run(tmp_path, "fp32", [[0, 10, 20, 30, 99], [0, 30, 40, 50, 99]], (0, 10, 20, 30, 40))
    bf16 = _run(tmp_path, "bf16", [[0, 12, 22, 32], [0, 26, 36, 46]])
    r = dtype_check.compare(fp32, bf16)
    assert r["frames"] == [10, 20, 30]
    assert r["mean_return_per_seed"] == {"a": [20.0, 40.0], "b": [22.0, 36.0]}
    assert r["paired_difference"] == [2.0, -4.0] and r["mean_difference"] == -1.0
    assert r["seed_spread_b"] == pytest.approx(np.std([22.0, 36.0], ddof=1))
    # paired t over d = (2, -4): mean -1, sd sqrt(18), t = -1 / (sqrt(18) / sqrt(2)) = -1/3
    assert r["t_statistic"] == pytest.approx(-1 / 3)
    assert r["within_noise"]
    assert r["train_frame"] == 35 and r["train_losses"]["b"]["critic_loss"] == [2.0, 3.0]
    assert "within noise: yes" in dtype_check.report(r)


def test_a_clear_gap_is_not_noise_and_bad_input_is_named(tmp_path):
    fp32 = _run(tmp_path, "fp32", [[0, 10, 10, 10], [0, 12, 12, 12], [0, 11, 11, 11]])
    bf16 = _run(tmp_path, "bf16", [[0, 110, 110, 110], [0, 112, 112, 111], [0, 111, 111, 111]])
    assert not dtype_check.compare(fp32, bf16)["within_noise"]
    with pytest.raises(FileNotFoundError, match="no seed_"):
        dtype_check.compare(fp32, tmp_path / "nowhere")
    two = _run(tmp_path, "two", [[0, 1, 2, 3], [0, 1, 2, 3]])
    with pytest.raises(ValueError, match="3 and 2 seeds"):
        dtype_check.compare(fp32, two)
