"""benchmarks/learning_check.py: a run against the published curves, and what its evaluations
cost, on a hand-made run."""

import csv
import json

import pytest

from benchmarks import learning_check
from configs import walker_drqv2_paper


def _csv(path, header, rows):
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def _line(t, msg):
    return f"2026-11-24 10:{t // 60:02d}:{t % 60:02d},000 I dear_jax: {msg}"


@pytest.fixture
def run(tmp_path):
    """Two seeds. Log rows of 100 frames per seed: [0,10] s, [10,30], [30,40], [40,59]; a stop;
    a resumed process whose first row (its compilation) is left out, then [90,98]. Evaluations:
    frame 200 ends at 28 s after 15 s (overlaps row 2 only), frame 400 ends at 45 s after 10 s
    (overlaps rows 3 and 4 by 5 s each)."""
    d = tmp_path / "run"
    for s, returns in enumerate([(20, 300, 900), (30, 100, 700)]):
        (d / f"seed_{s}").mkdir(parents=True)
        _csv(d / f"seed_{s}" / "train.csv", ["frame", "fps"], [(100, 1.0)])
        rows = zip((0, 100_000, 150_000), returns, (9.0, 15.0, 10.0))
        _csv(d / f"seed_{s}" / "eval.csv", ["frame", "episode_return", "eval_s"], rows)
    config = walker_drqv2_paper.get_config()
    config.seeds = 2
    (d / "config.json").write_text(json.dumps(config.to_dict()))
    lines = [
        _line(0, "frame 100 per seed: 1 frames/s in all"),
        _line(10, "frame 200 per seed: 1 frames/s in all"),
        _line(28, "eval @ 100,000 frames: return per seed [300.0, 100.0]"),
        _line(30, "frame 300 per seed: 1 frames/s in all"),
        _line(40, "frame 400 per seed: 1 frames/s in all"),
        _line(45, "eval @ 150,000 frames: return per seed [900.0, 700.0]"),
        _line(59, "frame 500 per seed: 1 frames/s in all"),
        _line(59, "stopped by SIGTERM at frame 500 per seed"),
        _line(90, "frame 600 per seed: 1 frames/s in all"),
        _line(98, "frame 700 per seed: 1 frames/s in all"),
    ]
    (d / "log.txt").write_text("\n".join(lines) + "\n")
    return d


def test_rows_an_evaluation_overlaps_are_not_training_alone(run):
    tp = learning_check.throughput(run)
    # 5 rows of 100 frames x 2 seeds in 10 + 20 + 10 + 19 + 8 = 67 s
    assert tp["rows"] == 5 and tp["overall_fps"] == pytest.approx(1000 / 67)
    # alone: rows 1 and 5, 400 frames in 18 s
    assert tp["rows_alone"] == 2 and tp["alone_fps"] == pytest.approx(400 / 18)
    assert tp["alone_from"] == "rows without an evaluation"
    assert tp["eval_busy"] == pytest.approx((15 + 10) / 67)
    assert tp["ratio"] == pytest.approx((400 / 18) / (1000 / 67))
    assert tp["tail_s"] == 0.0 and tp["ratio_with_tail"] == pytest.approx(tp["ratio"])


def test_the_closing_evaluation_after_the_last_row_counts_in_the_whole_run(run):
    log = run / "log.txt"
    log.write_text(log.read_text() + _line(110, "eval @ 200,000 frames: x") + "\n")
    for s in (0, 1):
        rows = [(0, 20, 9.0), (100_000, 300, 15.0), (150_000, 900, 10.0), (200_000, 950, 9.0)]
        _csv(run / f"seed_{s}" / "eval.csv", ["frame", "episode_return", "eval_s"], rows)
    tp = learning_check.throughput(run, alone_fps=30.0)
    # it runs from 101 s to 110 s, after the last row (98 s): 12 s more than the rows' 67
    assert tp["tail_s"] == pytest.approx(12.0) and tp["rows"] == 5
    assert tp["ratio_with_tail"] == pytest.approx(30.0 / (1000 / 79))


def test_training_alone_measured_apart(run):
    tp = learning_check.throughput(run, alone_fps=30.0)
    assert tp["alone_fps"] == 30.0 and tp["alone_from"] == "measured apart"
    assert tp["ratio"] == pytest.approx(30.0 / (1000 / 67))


def test_a_runs_first_part_alone(run):
    tp = learning_check.throughput(run, alone_fps=30.0, upto=300)
    # rows 1-2 (to frame 300): 200 frames x 2 seeds in 30 s; row 2 overlaps an evaluation
    assert tp["rows"] == 2 and tp["overall_fps"] == pytest.approx(400 / 30)
    assert tp["tail_s"] == 0.0 and tp["ratio"] == pytest.approx(30.0 / (400 / 30))
    # 20 s long, the evaluation logged at 45 s, after row 3 (frame 400), overlaps row 2 too
    for s in (0, 1):
        rows = [(0, 20, 9.0), (100_000, 300, 15.0), (150_000, 900, 20.0)]
        _csv(run / f"seed_{s}" / "eval.csv", ["frame", "episode_return", "eval_s"], rows)
    tp = learning_check.throughput(run, upto=300)
    assert tp["rows"] == 2 and tp["rows_alone"] == 1
    assert tp["eval_busy"] == pytest.approx((15 + 5) / 30)


def test_an_evaluation_without_its_duration_drops_the_row_it_ends_in(run):
    for s in (0, 1):
        rows = [(0, 20), (100_000, 300), (150_000, 900)]
        _csv(run / f"seed_{s}" / "eval.csv", ["frame", "episode_return"], rows)
    tp = learning_check.throughput(run)
    # ends at 28 s (row 2) and 45 s (row 4): rows 1, 3, 5 are left, 300 frames in 28 s
    assert tp["rows_alone"] == 3 and tp["alone_fps"] == pytest.approx(600 / 28)


def test_returns_against_the_published_median(run, tmp_path):
    ref = tmp_path / "ref.csv"
    ref.write_text("# published\nframe,seed_1,seed_2,median\n0,0,0,0\n200000,400,200,300\n")
    r = learning_check.compare(run, ref)
    assert r["method"] == "drqv2, bfloat16"
    assert [row["frame"] for row in r["rows"]] == [100_000, 150_000]
    assert r["rows"][0]["seeds"] == [300.0, 100.0] and r["rows"][0]["median"] == 200.0
    # the published median, 300 at 200k, linear from 0: 150 at 100k, 225 at 150k
    assert r["rows"][0]["published_median"] == pytest.approx(150.0)
    assert r["rows"][1]["median"] == 800.0
    assert r["rows"][1]["published_median"] == pytest.approx(225.0)


def test_a_run_ending_on_a_mark_lists_that_frame_once(run, tmp_path):
    for s in (0, 1):
        rows = [(0, 20, 9.0), (100_000, 300, 15.0), (200_000, 900, 10.0)]
        _csv(run / f"seed_{s}" / "eval.csv", ["frame", "episode_return", "eval_s"], rows)
    ref = tmp_path / "ref.csv"
    ref.write_text("# published\nframe,seed_1,median\n0,0,0\n200000,400,400\n")
    r = learning_check.compare(run, ref)
    assert [row["frame"] for row in r["rows"]] == [100_000, 200_000]


def test_a_run_evaluating_beside_every_row_has_no_ratio_unless_told(run, capsys):
    log = run / "log.txt"
    # an evaluation over the whole run: every row overlaps it
    log.write_text(log.read_text() + _line(99, "eval @ 150,000 frames: x") + "\n")
    for s in (0, 1):
        rows = [(0, 20, 9.0), (100_000, 300, 15.0), (150_000, 900, 99.0)]
        _csv(run / f"seed_{s}" / "eval.csv", ["frame", "episode_return", "eval_s"], rows)
    learning_check.main([str(run)])
    assert (
        "Training alone: unknown (no log row ran without an evaluation)" in capsys.readouterr().out
    )
    learning_check.main([str(run), "--alone-fps", "30"])
    assert "Training alone (measured apart): 30, so the run took" in capsys.readouterr().out
