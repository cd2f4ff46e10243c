"""The paper's claims, checked one by one on finished runs: `python -m dear_jax.report claims`.

The runs' seeds are pooled by experiment as `report table` pools them (one experiment per method
and task; a task's name carries its distraction setting). Each claim is checked per task on
per-seed figures, and says whether it holds and whether the seeds separate (every seed of one
side beyond every seed of the other) or overlap:

  return       a seed's mean return over its last `last` evaluations (up to `at` frames per
               seed): one evaluation swings far from the next, the mean of several is steadier
  frames to T  the first evaluated frame at which a seed's return reaches the threshold T; a
               seed that never does counts as infinite (it ran to its last evaluation without)
  |cos|        the mean |cos(z_A, z_E)| of a seed's last evaluation

The paper's claims, as checked here:
  1. DEAR's return >= SEAR's, on every task.
  2. DEAR is at least 25% more sample-efficient than each baseline: the median over seeds of
     DEAR's frames to T is at most 0.75 x the baseline's (a baseline whose median seed never
     reached T: at most 0.75 x the frames its seeds ran without reaching it).
  3. TED's return > SEAR's on the DeepMind Control tasks.
  4. DEAR's |cos| is far below SEAR's: by at least 10x here (the paper: 1e-7 against 0.1).
A claim without the runs it needs says so ("no data").
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np

from dear_jax import plot
from dear_jax.logger import format_table, read_csv

NAMES = {"dear": "DEAR", "sear": "SEAR", "ted": "TED", "drqv2": "DrQ-v2"}
BASELINES = ("drqv2", "sear", "ted")
EFFICIENCY = 0.75  # claim 2: DEAR's frames to T at most this fraction of a baseline's
COS_RATIO = 10.0  # claim 4: "far below" taken as at least this factor
COLUMNS = ("claim", "task", "evidence", "verdict")


@dataclasses.dataclass
class Seeds:
    """One experiment's per-seed figures (see the module docstring)."""

    runs: list[str]
    returns: np.ndarray
    frames_to: np.ndarray  # inf where the seed never reached the threshold
    last_frame: np.ndarray
    abs_cos: np.ndarray  # NaN where a log has no such column

    def median_frames(self) -> float:
        return float(np.median(self.frames_to))


def experiments(workdirs, threshold: float, at: int | None, last: int) -> dict:
    """{(task, method): Seeds} of the runs' pooled seeds. Two experiments of one method and task
    (e.g. two mask settings) are refused: give the runs of one experiment per method."""
    found = {}
    for pool in plot.pools([pathlib.Path(w) for w in workdirs]):
        task, method = plot.task_name(pool.config), pool.config["agent"]["method"]
        runs = [w.name for w in pool.workdirs]
        if (task, method) in found or pool.label:
            raise ValueError(
                f"{', '.join(runs)}: a second experiment of {method} on {task}"
                + (f" (setting {pool.label})" if pool.label else "")
                + "; give the runs of one experiment per method and task"
            )
        rows = []
        for _, lane in pool.seeds:
            evals = read_csv(lane / "eval.csv")
            keep = evals["frame"] <= (math.inf if at is None else at)
            if not keep.any():
                raise ValueError(f"{lane / 'eval.csv'} has no evaluation at or before {at:,}")
            frames, returns = evals["frame"][keep], evals["episode_return"][keep]
            hit = np.nonzero(returns >= threshold)[0]
            cos = evals.get("abs_cos_agent_env")
            rows.append(
                (
                    float(returns[-last:].mean()),
                    float(frames[hit[0]]) if hit.size else math.inf,
                    float(frames[-1]),
                    float(cos[keep][-1]) if cos is not None else math.nan,
                )
            )
        returns, frames_to, last_frame, abs_cos = map(np.array, zip(*rows))
        found[task, method] = Seeds(runs, returns, frames_to, last_frame, abs_cos)
    return found


def _spread(values: np.ndarray) -> str:
    return f"{values.mean():.1f} ± {values.std():.1f} (n={values.size})"


def _separate(high: np.ndarray, low: np.ndarray) -> str:
    return "seeds separate" if high.min() > low.max() else "seeds overlap"


def _frames(seeds: Seeds, threshold: float) -> str:
    reached = int(np.isfinite(seeds.frames_to).sum())
    median = seeds.median_frames()
    text = "never" if math.isinf(median) else f"{median / 1000:,.0f}k"
    return f"{text} ({reached}/{seeds.frames_to.size} reach {threshold:g})"


def _greater(claim, task, a, b, seeds, strict) -> dict:
    """Claim that method a's return is >= (strict: >) method b's on this task."""
    if a not in seeds or b not in seeds:
        missing = " and ".join(NAMES[m] for m in (a, b) if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    x, y = seeds[a].returns, seeds[b].returns
    holds = x.mean() > y.mean() if strict else x.mean() >= y.mean()
    order = (x, y) if holds else (y, x)
    evidence = f"{NAMES[a]} {_spread(x)} against {NAMES[b]} {_spread(y)}"
    verdict = f"{'holds' if holds else 'does not hold'} ({_separate(*order)})"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def _efficiency(task, baseline, seeds, threshold) -> dict:
    claim = f"DEAR >= 25% more sample-efficient than {NAMES[baseline]}"
    if "dear" not in seeds or baseline not in seeds:
        missing = " and ".join(NAMES[m] for m in ("dear", baseline) if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    d, b = seeds["dear"], seeds[baseline]
    evidence = f"frames to {threshold:g}: DEAR {_frames(d, threshold)}, "
    evidence += f"{NAMES[baseline]} {_frames(b, threshold)}"
    mine, theirs = d.median_frames(), b.median_frames()
    if math.isinf(mine):
        verdict = "undecided: neither reaches it" if math.isinf(theirs) else "does not hold"
    elif math.isinf(theirs):
        ran = float(b.last_frame.min())
        evidence += f" by {ran / 1000:,.0f}k"
        verdict = "holds" if mine <= EFFICIENCY * ran else "undecided: the baseline ran too short"
    else:
        verdict = "holds" if mine <= EFFICIENCY * theirs else "does not hold"
        evidence += f"; ratio {mine / theirs:.2f}"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def _cosine(task, seeds) -> dict:
    claim = "DEAR's |cos| far below SEAR's"
    if "dear" not in seeds or "sear" not in seeds:
        missing = " and ".join(NAMES[m] for m in ("dear", "sear") if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    d, s = seeds["dear"].abs_cos, seeds["sear"].abs_cos
    if np.isnan(d).any() or np.isnan(s).any():
        return dict(claim=claim, task=task, evidence="-", verdict="no data: logs without |cos|")
    ratio = s.mean() / d.mean()
    evidence = f"DEAR {d.mean():.1e}, SEAR {s.mean():.1e}: {ratio:.1f}x"
    holds = ratio >= COS_RATIO
    verdict = f"{'holds' if holds else 'does not hold'} ({_separate(s, d)})"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def check(workdirs, threshold: float = 500.0, at: int | None = None, last: int = 11) -> list:
    """The claims' rows ({claim, task, evidence, verdict}), per task of the runs."""
    found = experiments(workdirs, threshold, at, last)
    rows = []
    for task in dict.fromkeys(t for t, _ in found):
        seeds = {m: s for (t, m), s in found.items() if t == task}
        rows.append(_greater("DEAR's return >= SEAR's", task, "dear", "sear", seeds, False))
        rows += [_efficiency(task, b, seeds, threshold) for b in BASELINES]
        if not task.startswith("kitchen"):  # the DMC tasks
            rows.append(_greater("TED's return > SEAR's", task, "ted", "sear", seeds, True))
        rows.append(_cosine(task, seeds))
    return rows


def claims_table(workdirs, threshold=500.0, at=None, last=11, out=None) -> tuple[list, str]:
    """Rows and Markdown of the claims; with `out`, also writes out.md and out.json."""
    rows = check(workdirs, threshold, at, last)
    upto = "" if at is None else f" up to {at:,} frames"
    text = (
        f"The paper's claims: returns are each seed's mean over its last {last} evaluations"
        f"{upto}, mean ± population std over seeds; frames to a return of {threshold:g}, "
        "the median over seeds (a seed that never reaches it counts as never)\n\n"
        + format_table(COLUMNS, [[r[c] for c in COLUMNS] for r in rows])
        + "\n"
    )
    if out:
        path = pathlib.Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.with_suffix(".md").write_text(text)
        args = dict(threshold=threshold, at=at, last=last, runs=[str(w) for w in workdirs])
        path.with_suffix(".json").write_text(json.dumps(dict(args, claims=rows), indent=1))
    return rows, text
