"""benchmarks/eval_alternation.py: per-process offsets of evaluations from their neighbours."""

import json

import numpy as np

from benchmarks.eval_alternation import offsets, run_rows


def test_a_sawtooth_of_two_processes_is_read_as_their_offsets():
    # k = 1..5 interior: odd k sit 10 above their neighbours' mean, even k 10 below
    np.testing.assert_allclose(offsets(np.array([0, 10, 0, 10, 0, 10, 0.0]), 2), [-10, 10])
    # a straight line: every evaluation is its neighbours' mean
    np.testing.assert_allclose(offsets(np.arange(30.0) * 7, 3), [0, 0, 0], atol=1e-12)


def test_runs_without_distraction_or_with_few_evaluations_are_left_out(tmp_path):
    def run(name, distraction, evaluations, processes):
        lane = tmp_path / name / "seed_0"
        lane.mkdir(parents=True)
        (tmp_path / name / "config.json").write_text(
            json.dumps({"env": {"distraction": distraction}, "seeds": 1, "sweep": {}})
        )
        (tmp_path / name / "summary.json").write_text(json.dumps({"eval_processes": processes}))
        rows = "".join(f"{10000 * k},{100 + 10 * (k % 2)}\n" for k in range(evaluations))
        (lane / "eval.csv").write_text("frame,episode_return\n" + rows)
        return tmp_path / name

    assert run_rows(run("clean", "none", 30, 2)) == []
    assert run_rows(run("short", "medium", 10, 2)) == []
    (row,) = run_rows(run("saw", "medium", 30, 2))
    assert (row["processes"], row["evaluations"], row["offsets"]) == (2, 30, [-10.0, 10.0])
