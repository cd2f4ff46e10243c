"""Does bf16 learn like float32? Two runs of one config and the same seeds, compared seed by seed.

    python -m benchmarks.dtype_check FLOAT32_RUN BFLOAT16_RUN [--upto FRAMES] [--out F.json]

Made for one run per compute dtype; given two runs of the same dtype, it measures the noise
floor (GPU reductions are not bitwise deterministic, so reruns of one seed drift apart). Reads
both runs' eval.csv and train.csv (seed_i of one run against seed_i of the other: the same initial
parameters and first episodes) up to the last evaluation both have (or FRAMES), and prints
- the eval returns per seed at each common evaluation frame;
- per seed, the mean eval return over those evaluations (frame 0 left out: the untrained policy),
  the paired difference (second run - first), and a paired t-test over the seeds;
- the training losses of the last common log row (critic, mask, |cos(z_A, z_E)|).
"Within noise" here means: the mean paired difference is smaller than the spread of the second
run's per-seed means across seeds (their standard deviation), and the t-test does not reject
equality (p > 0.05).
Started on the GPU by `DTYPES="float32 bfloat16" LEARN_CONFIG=... bash benchmarks/train_device.sh
paper` (both runs side by side).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np
from scipy import stats

from dear_jax.logger import format_table, read_csv

TRAIN_COLUMNS = ("critic_loss", "mask_loss", "abs_cos_agent_env")


def _seeds(run: pathlib.Path) -> list[pathlib.Path]:
    dirs = sorted(run.glob("seed_*"), key=lambda d: int(d.name.split("_")[1]))
    if not dirs:
        raise FileNotFoundError(f"{run} has no seed_* folders: give a run's workdir")
    return dirs


def _dtype(run) -> str:
    config = pathlib.Path(run) / "config.json"
    return json.loads(config.read_text())["agent"]["compute_dtype"] if config.is_file() else "?"


def compare(run_a, run_b, upto: int | None = None) -> dict:
    seeds_a, seeds_b = _seeds(pathlib.Path(run_a)), _seeds(pathlib.Path(run_b))
    if len(seeds_a) != len(seeds_b):
        raise ValueError(
            f"the runs have {len(seeds_a)} and {len(seeds_b)} seeds; give runs of the same"
        )
    evals = [[read_csv(d / "eval.csv") for d in dirs] for dirs in (seeds_a, seeds_b)]
    frames = sorted(set.intersection(*(set(e["frame"].astype(int)) for run in evals for e in run)))
    frames = [int(f) for f in frames if 0 < f <= (upto if upto is not None else f)]
    if not frames:
        raise ValueError(
            "the runs have no common evaluation after frame 0"
            + (f" and up to {upto:,} frames" if upto is not None else "")
        )

    def returns(e):
        return np.array([e["episode_return"][e["frame"] == f][0] for f in frames])

    per_frame = np.array([[returns(e) for e in run] for run in evals])  # [dtype, seed, frame]
    means = per_frame.mean(-1)  # [dtype, seed]
    diff = means[1] - means[0]
    test = stats.ttest_rel(means[1], means[0])
    trains = [[read_csv(d / "train.csv") for d in dirs] for dirs in (seeds_a, seeds_b)]
    last = min(t["frame"][-1] for run in trains for t in run)
    last = min(last, frames[-1]) if upto is not None else last
    losses = {
        dtype: {
            col: [float(t[col][t["frame"] <= last][-1]) for t in run if col in t]
            for col in TRAIN_COLUMNS
        }
        for dtype, run in zip("ab", trains)
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
        "t_statistic": float(test.statistic),
        "p_value": float(test.pvalue),
        "within_noise": bool(abs(diff.mean()) < spread and test.pvalue > 0.05),
        "train_frame": int(last),
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
