"""How far the evaluations of each evaluation process stand from their neighbours in time.

    python -m benchmarks.eval_alternation RUN [RUN ...] [--out FILE]

A run with N evaluation processes (`eval_processes`) runs its k-th evaluation in process
k mod N. Where the processes composited different built-in background videos (as they did
before a run's processes shared one set: docs/method.md, decision 5), one process's returns
sit above or below the others' at neighbouring frames, a sawtooth on the curve. For every lane of every run given
with a distraction, this prints, per process (with one process: per parity of k, the
reference that the curve's own swings give), the mean over its evaluations (but the first and
last) of return - the mean of the two neighbouring evaluations' returns, and the median gap
between the two groups over the lanes of each kind (lanes of at least MIN_EVALUATIONS
evaluations: fewer say little). Nothing is trained; it reads the logs.
Writes JSON (--out).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from benchmarks.common import save_json
from dear_jax import lanes
from dear_jax.logger import read_csv

MIN_EVALUATIONS = 20


def offsets(returns: np.ndarray, processes: int) -> list[float]:
    """Per process p: the mean of returns[k] - (returns[k-1] + returns[k+1]) / 2 over the
    interior evaluations k with k mod processes == p (NaN where it has none)."""
    k = np.arange(1, len(returns) - 1)
    gap = returns[k] - (returns[k - 1] + returns[k + 1]) / 2
    return [float(np.mean(gap[k % processes == p])) if np.any(k % processes == p) else np.nan
            for p in range(processes)]  # fmt: skip


def run_rows(workdir: pathlib.Path) -> list[dict]:
    summary = json.loads((workdir / "summary.json").read_text())
    config = json.loads((workdir / "config.json").read_text())
    processes = summary.get("eval_processes", 1)
    if config["env"]["distraction"] == "none":
        return []
    rows = []
    for lane in (d for dirs in lanes.groups(workdir).values() for d in dirs):
        returns = read_csv(lane / "eval.csv")["episode_return"]
        if len(returns) < MIN_EVALUATIONS:
            continue
        rows.append(
            {
                "run": f"{workdir.parent.name}/{workdir.name}",
                "lane": lane.name,
                "processes": processes,
                "evaluations": int(len(returns)),
                "offsets": offsets(returns, max(processes, 2)),
            }
        )
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=pathlib.Path)
    parser.add_argument("--out")
    args = parser.parse_args()
    rows = [row for run in args.runs for row in run_rows(run)]
    print("| run | lane | processes | evaluations | per process (one: per parity) |")
    print("| --- | --- | ---: | ---: | --- |")
    for r in rows:
        cells = ", ".join(f"{x:+.1f}" for x in r["offsets"])
        print(f"| {r['run']} | {r['lane']} | {r['processes']} | {r['evaluations']} | {cells} |")
    result = {"rows": rows}
    for kind, several in (("one process", False), ("several processes", True)):
        gaps = [
            abs(r["offsets"][0] - r["offsets"][1]) for r in rows if (r["processes"] > 1) == several
        ]
        if gaps:
            result[kind] = {
                "lanes": len(gaps),
                "median_gap": float(np.median(gaps)),
                "max_gap": max(gaps),
            }
            print(
                f"{kind}: groups 0 and 1 apart by a median {np.median(gaps):.1f}, at most {max(gaps):.1f}, over {len(gaps)} lanes"
            )
    save_json(result, args.out)


if __name__ == "__main__":
    main()
