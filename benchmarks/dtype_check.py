"""Does bf16 learn like float32? Two runs of one config and the same seeds, compared seed by seed.

    python -m benchmarks.dtype_check FLOAT32_RUN BFLOAT16_RUN [--upto FRAMES] [--out F.json]

Made for one run per compute dtype; given two runs of the same dtype, it measures the noise
floor (GPU reductions are not bitwise deterministic, so reruns of one seed drift apart). Reads
both runs' eval.csv and train.csv (seed_i of one run against seed_i of the other: the same initial
parameters and first episodes) up to the last evaluation both have (or FRAMES), and prints
- the eval returns per seed at each common evaluation frame;
- per seed, the mean eval return over those evaluations (frame 0 left out: the untrained policy),
  the paired difference (second run - first), and a paired t-test over the seeds;
- the training losses (critic, mask, |cos(z_A, z_E)|) of the last log frame both runs have.
"Within noise" here means: the mean paired difference is smaller than the spread of the second
run's per-seed means across seeds (their standard deviation), and the t-test does not reject
equality (p > 0.05).
The two runs train side by side on one GPU, e.g. `bash benchmarks/device.sh start dear_f32 0
--config=configs/walker_dear.py --config.agent.compute_dtype=float32 start dear_bf16 0
--config=configs/walker_dear.py --config.agent.compute_dtype=bfloat16`.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np
from scipy import stats

from dear_jax.logger import format_table, read_csv

TRAIN_COLUMNS = ("critic_loss", "mask_loss", "abs_cos_agent_env")


def _seeds(run: pathlib.Path) -> dict[str, pathlib.Path]:
    dirs = {d.name: d for d in run.glob("seed_*") if d.is_dir()}
    if not dirs:
        raise FileNotFoundError(f"{run} has no seed_* folders: give a run's workdir")
    return dict(sorted(dirs.items(), key=lambda item: int(item[0].split("_")[1])))


def _paired_test(diff: np.ndarray) -> tuple[float, float]:
    """Paired t-test of the differences against 0; (t, p). Equal differences have no spread:
    all 0 is no difference (p = 1), any other constant a sure one (p = 0)."""
    if np.all(diff == diff[0]):
        return (0.0, 1.0) if diff[0] == 0 else (math.copysign(math.inf, diff[0]), 0.0)
    test = stats.ttest_1samp(diff, 0.0)
    return float(test.statistic), float(test.pvalue)


def _dtype(run) -> str:
    config = pathlib.Path(run) / "config.json"
    return json.loads(config.read_text())["agent"]["compute_dtype"] if config.is_file() else "?"


def _logs(dirs, name: str, upto: int | None) -> tuple[list[list[dict]], list[int]]:
    """Both runs' `name` CSVs per seed, and the frames (after 0, up to `upto`) at which every one
    of them has a row."""
    logs = [[read_csv(d / name) for d in run] for run in dirs]
    frames = set.intersection(*({int(f) for f in log["frame"]} for run in logs for log in run))
    frames = sorted(f for f in frames if 0 < f <= (upto if upto is not None else f))
    if not frames:
        until = f" up to {upto:,} frames" if upto is not None else ""
        raise ValueError(f"the runs' {name} have no common frame after 0{until}")
    return logs, frames


def compare(run_a, run_b, upto: int | None = None) -> dict:
    seeds_a, seeds_b = _seeds(pathlib.Path(run_a)), _seeds(pathlib.Path(run_b))
    if list(seeds_a) != list(seeds_b):
        raise ValueError(
            f"the runs hold different seeds ({', '.join(seeds_a)} and {', '.join(seeds_b)}); "
            "give two runs of the same seeds"
        )
    dirs = (list(seeds_a.values()), list(seeds_b.values()))
    evals, frames = _logs(dirs, "eval.csv", upto)

    def returns(e):
        return np.array([e["episode_return"][e["frame"] == f][0] for f in frames])

    per_frame = np.array([[returns(e) for e in run] for run in evals])  # [dtype, seed, frame]
    means = per_frame.mean(-1)  # [dtype, seed]
    diff = means[1] - means[0]
    t, p = _paired_test(diff)
    # Training losses at the last log frame every seed of both runs has (up to `upto`).
    trains, train_frames = _logs(dirs, "train.csv", upto)
    at = train_frames[-1]
    losses = {
        name: {
            col: [float(log[col][log["frame"] == at][0]) for log in run if col in log]
            for col in TRAIN_COLUMNS
        }
        for name, run in zip("ab", trains)
    }
    spread = float(means[1].std(ddof=1)) if means.shape[1] > 1 else float("nan")
    return {
        "runs": {"a": str(run_a), "b": str(run_b)},
        "dtypes": {"a": _dtype(run_a), "b": _dtype(run_b)},
        "frames": frames,
        "returns": {"a": per_frame[0].tolist(), "b": per_frame[1].tolist()},
        "mean_return_per_seed": {"a": means[0].tolist(), "b": means[1].tolist()},
        "paired_difference": diff.tolist(),
        "mean_difference": float(diff.mean()),
        "seed_spread_b": spread,
        "t_statistic": t,
        "p_value": p,
        "within_noise": bool(abs(diff.mean()) <= spread and p > 0.05),
        "train_frame": at,
        "train_losses": losses,
    }


def report(r: dict) -> str:
    seeds = len(r["paired_difference"])
    rows = [
        [f"{f:,}"] + [f"{r['returns'][d][s][i]:.1f}" for d in "ab" for s in range(seeds)]
        for i, f in enumerate(r["frames"])
    ]
    rows.append(["mean"] + [f"{m:.1f}" for d in "ab" for m in r["mean_return_per_seed"][d]])
    head = ["frame"] + [f"{d.upper()} seed {s}" for d in "ab" for s in range(seeds)]
    lines = [
        f"A = {r['runs']['a']} ({r['dtypes']['a']}), B = {r['runs']['b']} ({r['dtypes']['b']})",
        "Eval returns at the evaluations both runs have (mean: over those, per seed)",
        "",
        format_table(head, rows),
        "",
        "paired difference B - A per seed: "
        + ", ".join(f"{d:+.1f}" for d in r["paired_difference"])
        + f"; mean {r['mean_difference']:+.1f} against a seed spread (std) of "
        f"{r['seed_spread_b']:.1f}; paired t = {r['t_statistic']:.2f}, p = {r['p_value']:.2f}",
        f"within noise: {'yes' if r['within_noise'] else 'no'}",
        "",
        f"training losses at frame {r['train_frame']:,} (per seed):",
    ]
    for dtype, cols in r["train_losses"].items():
        text = "; ".join(
            f"{c} " + ", ".join(f"{v:.3g}" for v in vs) for c, vs in cols.items() if vs
        )
        lines.append(f"  {dtype.upper()}: {text}")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", help="workdir of the reference run (float32)")
    parser.add_argument("run_b", help="workdir of the run compared with it (bfloat16)")
    parser.add_argument("--upto", type=int, default=None, help="compare up to this frame")
    parser.add_argument("--out", default=None, help="JSON path")
    args = parser.parse_args(argv)
    try:
        r = compare(args.run_a, args.run_b, args.upto)
    except (FileNotFoundError, ValueError) as e:
        parser.error(str(e))
    print(report(r))
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(r, indent=1))
    return r


if __name__ == "__main__":
    main()
