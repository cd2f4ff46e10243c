"""Does bf16 learn like float32? Two runs of one config and the same seeds, one per compute dtype.

    python -m benchmarks.dtype_check FLOAT32_RUN BFLOAT16_RUN [--out results/dtype_check.json]

Reads both runs' eval.csv and train.csv (seed by seed: seed_i of one run against seed_i of the
other, which start from the same parameters and see the same first episodes) up to the last
evaluation both have, and prints
- the eval returns per seed at each common evaluation frame;
- per seed, the mean eval return over those evaluations (frame 0 left out: the untrained policy),
  the paired difference bf16 - float32, and a paired t-test over the seeds;
- the training losses of the last common log row (critic, mask, |cos(z_A, z_E)|).
"Within noise" here means: the mean paired difference is smaller than the spread of the per-seed
means across seeds (their standard deviation), and the t-test does not reject equality (p > 0.05).
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


def compare(fp32_run, bf16_run) -> dict:
    fp32, bf16 = _seeds(pathlib.Path(fp32_run)), _seeds(pathlib.Path(bf16_run))
    if len(fp32) != len(bf16):
        raise ValueError(f"the runs have {len(fp32)} and {len(bf16)} seeds; give runs of the same")
    evals = [[read_csv(d / "eval.csv") for d in dirs] for dirs in (fp32, bf16)]
    frames = sorted(set.intersection(*(set(e["frame"].astype(int)) for run in evals for e in run)))
    frames = [int(f) for f in frames if f > 0]
    if not frames:
        raise ValueError("the runs have no common evaluation after frame 0")

    def returns(e):
        return np.array([e["episode_return"][e["frame"] == f][0] for f in frames])

    per_frame = np.array([[returns(e) for e in run] for run in evals])  # [dtype, seed, frame]
    means = per_frame.mean(-1)  # [dtype, seed]
    diff = means[1] - means[0]
    test = stats.ttest_rel(means[1], means[0])
    trains = [[read_csv(d / "train.csv") for d in dirs] for dirs in (fp32, bf16)]
    last = min(t["frame"][-1] for run in trains for t in run)
    losses = {
        dtype: {
            col: [float(t[col][t["frame"] <= last][-1]) for t in run if col in t]
            for col in TRAIN_COLUMNS
        }
        for dtype, run in zip(("float32", "bfloat16"), trains)
    }
    spread = float(means[1].std(ddof=1)) if means.shape[1] > 1 else float("nan")
    return {
        "runs": {"float32": str(fp32_run), "bfloat16": str(bf16_run)},
        "frames": frames,
        "returns": {"float32": per_frame[0].tolist(), "bfloat16": per_frame[1].tolist()},
        "mean_return_per_seed": {"float32": means[0].tolist(), "bfloat16": means[1].tolist()},
        "paired_difference": diff.tolist(),
        "mean_difference": float(diff.mean()),
        "seed_spread_bf16": spread,
        "t_statistic": float(test.statistic),
        "p_value": float(test.pvalue),
        "within_noise": bool(abs(diff.mean()) < spread and test.pvalue > 0.05),
        "train_frame": int(last),
        "train_losses": losses,
    }


def report(r: dict) -> str:
    seeds = len(r["paired_difference"])
    rows = [
        [f"{f:,}"]
        + [f"{r['returns'][d][s][i]:.1f}" for d in ("float32", "bfloat16") for s in range(seeds)]
        for i, f in enumerate(r["frames"])
    ]
    rows.append(
        ["mean"]
        + [f"{m:.1f}" for d in ("float32", "bfloat16") for m in r["mean_return_per_seed"][d]]
    )
    head = ["frame"] + [f"{d} seed {s}" for d in ("fp32", "bf16") for s in range(seeds)]
    lines = [
        "Eval returns at the evaluations both runs have (mean: over those, per seed)",
        "",
        format_table(head, rows),
        "",
        "paired difference bf16 - fp32 per seed: "
        + ", ".join(f"{d:+.1f}" for d in r["paired_difference"])
        + f"; mean {r['mean_difference']:+.1f} against a seed spread (std) of "
        f"{r['seed_spread_bf16']:.1f}; paired t = {r['t_statistic']:.2f}, p = {r['p_value']:.2f}",
        f"within noise: {'yes' if r['within_noise'] else 'no'}",
        "",
        f"training losses at frame {r['train_frame']:,} (per seed):",
    ]
    for dtype, cols in r["train_losses"].items():
        text = "; ".join(f"{c} " + ", ".join(f"{v:.3g}" for v in vs) for c, vs in cols.items() if vs)
        lines.append(f"  {dtype}: {text}")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("float32_run")
    parser.add_argument("bfloat16_run")
    parser.add_argument("--out", default=None, help="JSON path")
    args = parser.parse_args(argv)
    try:
        r = compare(args.float32_run, args.bfloat16_run)
    except (FileNotFoundError, ValueError) as e:
        parser.error(str(e))
    print(report(r))
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(r, indent=1))
    return r


if __name__ == "__main__":
    main()
