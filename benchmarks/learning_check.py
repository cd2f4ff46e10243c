"""A run's evaluation returns against DrQ-v2's published walker-walk curves.

    python -m benchmarks.learning_check RUN [--reference CSV] [--out-png F] [--out F.json]

RUN is a workdir of `run.py` (e.g. configs/walker_drqv2_paper.py). The reference is DrQ-v2's
published evaluation returns per seed (facebookresearch/drqv2 curves/dmc_walker_walk.csv, kept
in wide form with their median: benchmarks/results/walker_drqv2_paper_h100/). Prints, at every
100k frames the run reached and at its last evaluation, each seed's return, the run's median and
the published median (linear between its points, every 20k frames); draws both curves (the
published seeds' 25-75% band shaded) and writes JSON.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import pathlib
import re

import numpy as np

from benchmarks.common import save_json
from dear_jax.plot import load_curves

REFERENCE = "benchmarks/results/walker_drqv2_paper_h100/drqv2_published_walker_walk.csv"


def load_reference(path) -> tuple[np.ndarray, np.ndarray]:
    """(frames [N], returns [N, seeds]) of the published curves (the median column left out)."""
    lines = [ln for ln in pathlib.Path(path).read_text().splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    seeds = [i for i, name in enumerate(header) if name.startswith("seed_")]
    return table[:, 0], table[:, seeds]


def compare(run, reference=REFERENCE, alone_fps=None, upto=None) -> dict:
    (curve,) = load_curves(run, "episode_return")
    both = ~np.isnan(curve.y).any(0)  # frames every seed has evaluated
    frames, returns = curve.x[both], curve.y[:, both]
    ref_frames, ref = load_reference(reference)
    ref_median = np.median(ref, 1)
    marks = list(range(100_000, int(frames[-1]) + 1, 100_000))
    rows = []
    for mark in sorted({*marks, int(frames[-1])}):
        i = int(np.argmin(np.abs(frames - mark)))
        rows.append(
            dict(
                frame=int(frames[i]),
                seeds=returns[:, i].round(1).tolist(),
                median=float(np.median(returns[:, i])),
                published_median=float(np.interp(frames[i], ref_frames, ref_median)),
            )
        )
    config = json.loads((pathlib.Path(run) / "config.json").read_text())
    agent = config["agent"]
    return dict(
        run=str(run),
        method=f"{agent['method']}, {agent.get('compute_dtype', 'float32')}",
        reference=str(reference),
        rows=rows,
        frames=frames.tolist(),
        returns=returns.tolist(),
        ref_frames=ref_frames.tolist(),
        ref_median=ref_median.tolist(),
        ref_quartiles=np.percentile(ref, [25, 75], axis=1).tolist(),
        throughput=throughput(run, alone_fps, upto),
    )


_STAMP = r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+) "


def throughput(run, alone_fps: float | None = None, upto: int | None = None) -> dict | None:
    """Frames/s in all of a run, from its log.txt's timestamped rows, and how much of its
    training time had an evaluation running beside it; None without such a log.

    A row is the span between two consecutive "frame N per seed" lines of one process (a stop or
    a resume starts a new process, whose first row, with its compilation, is left out like the
    run's first). An evaluation runs from its "eval @" line's time less its `eval_s` (seed_0's
    eval.csv) to that line. Rows that no evaluation overlaps are "training alone"; at the paper's
    rate an evaluation on the H100 runs most of the time, so there may be none, and the ratio then
    needs `alone_fps`: training alone measured apart (benchmarks/train.py, same loop).
    `tail_s`: from the last row to the end of the last evaluation (the closing one), when that
    ends later; `ratio_with_tail` counts it as run time too. `upto`: only the rows up to that
    frame per seed (a run's first part, against a shorter run; no tail).
    """
    run = pathlib.Path(run)
    log = run / "log.txt"
    if not log.exists():
        return None
    lanes = sum(1 for d in run.iterdir() if (d / "train.csv").exists())
    lane0 = sorted(d for d in run.iterdir() if (d / "eval.csv").exists())
    eval_s = {}  # an evaluation's first frame -> its seconds (a redone one: the redo's)
    if lane0:
        with open(lane0[0] / "eval.csv", newline="") as f:
            for row in csv.DictReader(f):
                eval_s[int(row["frame"])] = float(row.get("eval_s") or "nan")
    spans, evals, last = [], [], None  # spans: (start s, end s, frames per lane)
    last_row_t = None
    for line in log.read_text().splitlines():
        stamp = re.match(_STAMP, line)
        if not stamp:
            continue
        t = datetime.datetime.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
        if m := re.search(r"frame (\d+) per seed: \d+ frames/s in all", line):
            frame = int(m.group(1))
            if upto is not None and frame > upto:
                continue  # later rows left out; evaluations logged after them still count
            if last is not None and frame > last[1]:
                spans.append((last[0], t, frame - last[1]))
            last = (t, frame)
            last_row_t = t
        elif m := re.search(r"eval @ ([\d,]+) frames", line):
            took = eval_s.get(int(m.group(1).replace(",", "")), math.nan)
            # Without its eval_s (an older log) the span is unknown: the row it ends in goes.
            evals.append((t - (took if math.isfinite(took) else 1e-6), t))
        elif "stopped by" in line:
            last = None
    if not spans:
        return None

    def rate(rows):
        return sum(f for _, _, f in rows) * lanes / sum(b - a for a, b, _ in rows)

    def overlap(a, b):
        return sum(max(0.0, min(b, e1) - max(a, e0)) for e0, e1 in evals)

    alone = [r for r in spans if overlap(r[0], r[1]) == 0.0]
    overall = rate(spans)
    tail = 0.0 if upto is not None else max([0.0] + [end - last_row_t for _, end in evals])
    row_s = sum(b - a for a, b, _ in spans)
    alone_rows = rate(alone) if alone else math.nan
    reference = alone_fps if alone_fps else alone_rows
    return dict(
        overall_fps=overall,
        alone_fps=reference,
        alone_from="measured apart" if alone_fps else "rows without an evaluation",
        rows_alone=len(alone),
        rows=len(spans),
        eval_busy=sum(overlap(a, b) for a, b, _ in spans) / row_s,
        ratio=reference / overall,
        tail_s=tail,
        ratio_with_tail=reference / overall * (row_s + tail) / row_s,
    )


def plot(result: dict, out_png) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    k = 1e-3
    rf = np.asarray(result["ref_frames"]) * k
    lo, hi = result["ref_quartiles"]
    ax.fill_between(rf, lo, hi, color="tab:gray", alpha=0.25, label="published: 25-75% of 10 seeds")
    ax.plot(rf, result["ref_median"], color="black", lw=2, label="published DrQ-v2: median")
    frames, returns = np.asarray(result["frames"]) * k, np.asarray(result["returns"])
    for s, seed in enumerate(returns):
        ax.plot(
            frames,
            seed,
            color="tab:blue",
            lw=0.8,
            alpha=0.5,
            label="this run: seeds" if not s else None,
        )
    ax.plot(frames, np.median(returns, 0), color="tab:blue", lw=2, label="this run: median")
    ax.set_xlim(0, max(frames[-1], 100) * 1.05)
    ax.set_xlabel("environment frames (k)")
    ax.set_ylabel("evaluation return")
    ax.set_title(f"walker-walk: this run ({result['method']}) and published DrQ-v2")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    pathlib.Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    print(f"wrote {out_png}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("run")
    p.add_argument("--reference", default=REFERENCE)
    p.add_argument("--out-png", default=None)
    p.add_argument("--out", default=None)
    p.add_argument(
        "--alone-fps",
        type=float,
        default=None,
        help="frames/s of the same loop without evaluation, measured apart (benchmarks/train.py)",
    )
    p.add_argument(
        "--upto",
        type=int,
        default=None,
        help="frames per seed: the run's throughput over its log rows up to there only",
    )
    args = p.parse_args(argv)
    result = compare(args.run, args.reference, args.alone_fps, args.upto)
    print("| frames per seed | return per seed | median | published median |\n|---:|---|---:|---:|")
    for r in result["rows"]:
        seeds = ", ".join(f"{v:.0f}" for v in r["seeds"])
        print(f"| {r['frame']:,} | {seeds} | {r['median']:.0f} | {r['published_median']:.0f} |")
    if tp := result["throughput"]:
        print(
            f"frames/s in all: {tp['overall_fps']:.0f} over the run; an evaluation ran during "
            f"{tp['eval_busy']:.0%} of its training time; {tp['rows_alone']} of {tp['rows']} log "
            "rows had none."
        )
        if math.isnan(tp["alone_fps"]):
            print(
                "Training alone: unknown (no log row ran without an evaluation); pass "
                "--alone-fps, the same loop's rate measured apart, for the run's ratio to it"
            )
        else:
            print(
                f"Training alone ({tp['alone_from']}): {tp['alone_fps']:.0f}, so the run took "
                f"{tp['ratio']:.2f}x the time of its training alone over its log rows, "
                f"{tp['ratio_with_tail']:.2f}x with the {tp['tail_s']:.0f} s after its last row "
                "(its closing evaluation)"
            )
    if args.out_png:
        plot(result, args.out_png)
    save_json(result, args.out)
    return result


if __name__ == "__main__":
    main()
