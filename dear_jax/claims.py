"""The paper's claims, checked one by one on finished runs: `python -m dear_jax.report claims`.

The runs' seeds are pooled by experiment as `report table` pools them (one experiment per method
and task; a task's name carries its distraction setting). Each claim is checked per task on
per-seed figures, and says whether it holds and whether the seeds separate (every seed of one
side beyond every seed of the other) or overlap:

  return       a seed's mean return over its last `last` evaluations (up to `at` frames per
               seed): one evaluation swings far from the next, the mean of several is steadier
  frames to T  the first evaluated frame at which a seed's return reaches the threshold T; a
               seed that never does took more than its last evaluated frame, so the median
               over seeds is known between bounds (one seed never reaching T: the median of
               three is still exact if the other two did)
  |cos|        the mean |cos(z_A, z_E)| of a seed's last evaluation

The paper's claims, as checked here:
  1. DEAR's return >= SEAR's, on every task.
  2. DEAR is at least 25% more sample-efficient than each baseline: the median over seeds of
     DEAR's frames to T is at most 0.75 x the baseline's. It holds when DEAR's upper bound is
     at most 0.75 x the baseline's lower bound, does not when DEAR's lower bound is above 0.75 x
     the baseline's upper bound, and is undecided between (runs too short to tell).
  3. TED's return > SEAR's on the DeepMind Control tasks.
  4. DEAR's |cos| is far below SEAR's: by at least 10x here (the paper: 1e-7 against 0.1).
A claim without the runs it needs says so ("no data"). Claims 1, 3 and 4 compare both sides at
one frame: where a run stopped early, every seed's figures are taken up to the shortest run's
last evaluation, and the evidence says at which frame.
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
# The return at which a seed reaches its task (frames to T) where no threshold is given: 500 of a
# DMC task's 1000; in the kitchen, whose evaluation return is its success rate, 1 (every episode).
DMC_THRESHOLD, KITCHEN_THRESHOLD = 500.0, 1.0


@dataclasses.dataclass
class Seeds:
    """One experiment's per-seed figures (see the module docstring)."""

    returns: np.ndarray
    frames_to: np.ndarray  # inf where the seed never reached the threshold
    last_frame: np.ndarray
    abs_cos: np.ndarray  # NaN where a log has no such column
    # Each seed's evaluations (frames, returns, |cos|), to take the figures at an earlier frame.
    series: tuple = ()
    last: int = 11
    slack: float = plot.SLACK  # plot.slack of the runs' config, as `experiments` reads them

    def upto(self, frame: float) -> Seeds:
        """Returns and |cos| of the evaluations up to `frame` (within `slack`)."""
        if not self.series:
            raise ValueError("these figures carry no evaluations to take at another frame")
        rows = []
        for frames, returns, cos in self.series:
            keep = frames <= frame + self.slack
            if not keep.any():
                raise ValueError(f"a seed has no evaluation at or before {frame:,.0f} frames")
            rows.append((returns[keep][-self.last :].mean(), frames[keep][-1], cos[keep][-1]))
        returns, last_frame, abs_cos = map(np.array, zip(*rows))
        return dataclasses.replace(self, returns=returns, last_frame=last_frame, abs_cos=abs_cos)

    def median_bounds(self) -> tuple[float, float]:
        """`median_frames_to` of these seeds."""
        return median_frames_to(self.frames_to, self.last_frame)


def median_frames_to(frames_to, last_frame) -> tuple[float, float]:
    """(lower, upper) bounds of the median over seeds of the frames to T (inf where a seed never
    reached T): such a seed took more than its last evaluated frame (lower: that frame; upper:
    inf). Where most seeds reached T the two are equal: the median."""
    frames_to, last_frame = np.asarray(frames_to, float), np.asarray(last_frame, float)
    lower = np.median(np.where(np.isinf(frames_to), last_frame, frames_to))
    return float(lower), float(np.median(frames_to))


def is_kitchen(env_task: str) -> bool:
    """Whether `env_task` (an env's name, e.g. "kitchen-light") is a Franka Kitchen task."""
    from envs import kitchen

    return env_task in kitchen.TASKS


def default_threshold(env_task: str) -> float:
    """The return at which a seed of `env_task` reaches it, where no threshold is given."""
    return KITCHEN_THRESHOLD if is_kitchen(env_task) else DMC_THRESHOLD


def experiments(workdirs, threshold: float | None, at: int | None, last: int) -> dict:
    """{(task, method): Seeds} of the runs' pooled seeds; threshold None: each task's
    `default_threshold`. Two experiments of one method and task (e.g. two mask settings) are
    refused: give the runs of one experiment per method."""
    if last < 1:
        raise ValueError(f"last must be at least 1 evaluation, got {last}")
    found = {}
    for pool in plot.pools([pathlib.Path(w) for w in workdirs]):
        task, method = plot.task_name(pool.config), pool.config["agent"]["method"]
        target = default_threshold(pool.config["env"]["task"]) if threshold is None else threshold
        runs = ", ".join(w.name for w in pool.workdirs)
        if pool.changed:
            raise ValueError(
                f"{runs}: {method} with its own {', '.join(pool.changed)} ({pool.label}: a sweep "
                "or a weight setting); claims compare the methods as the paper sets them"
            )
        if (task, method) in found:
            raise ValueError(
                f"{runs}: a second experiment of {method} on {task}; give the runs of one "
                "experiment per method and task"
            )
        rows, series = [], []
        for _, lane in pool.seeds:
            evals = read_csv(lane / "eval.csv")
            if "episode_return" not in evals or not len(evals["episode_return"]):
                raise ValueError(f"{lane / 'eval.csv'} holds no evaluation")
            keep = evals["frame"] <= (math.inf if at is None else at + plot.slack(pool.config))
            if not keep.any():
                raise ValueError(f"{lane / 'eval.csv'} has no evaluation at or before {at:,}")
            frames, returns = evals["frame"][keep], evals["episode_return"][keep]
            hit = np.nonzero(returns >= target)[0]
            cos = evals.get("abs_cos_agent_env", np.full(len(keep), math.nan))[keep]
            rows.append(
                (
                    float(returns[-last:].mean()),
                    float(frames[hit[0]]) if hit.size else math.inf,
                    float(frames[-1]),
                    float(cos[-1]),
                )
            )
            series.append((frames, returns, cos))
        returns, frames_to, last_frame, abs_cos = map(np.array, zip(*rows))
        found[task, method] = Seeds(
            returns, frames_to, last_frame, abs_cos, tuple(series), last, plot.slack(pool.config)
        )
    return found


def _spread(values: np.ndarray, digits: int = 1) -> str:
    return f"{values.mean():.{digits}f} ± {values.std():.{digits}f} (n={values.size})"


def _separate(high: np.ndarray, low: np.ndarray) -> str:
    if high.size == low.size == 1:
        return "one seed each"
    return "seeds separate" if high.min() > low.max() else "seeds overlap"


def _k(frames: float) -> str:
    return f"{frames / 1000:,.0f}k"


def _frames(seeds: Seeds, threshold: float) -> str:
    reached = int(np.isfinite(seeds.frames_to).sum())
    lower, upper = seeds.median_bounds()
    if lower == upper:
        text = _k(upper)
    elif math.isinf(upper):
        text = f"not by {_k(lower)}"
    else:
        text = f"{_k(lower)}-{_k(upper)}"
    return f"{text} ({reached}/{seeds.frames_to.size} reach {threshold:g})"


def _at_one_frame(x: Seeds, y: Seeds) -> tuple[Seeds, Seeds, str]:
    """x and y up to the last evaluation of the shortest run among them, and the evidence's
    note of that frame ("" where every run ended there)."""
    ends = np.concatenate([x.last_frame, y.last_frame])
    if ends.max() <= ends.min() + min(x.slack, y.slack):
        return x, y, ""
    end = ends.min()
    return x.upto(end), y.upto(end), f", at {_k(end)} (the shortest run's last evaluation)"


def _greater(claim, task, a, b, seeds, strict) -> dict:
    """Claim that method a's return is >= (strict: >) method b's on this task."""
    if a not in seeds or b not in seeds:
        missing = " and ".join(NAMES[m] for m in (a, b) if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    sa, sb, note = _at_one_frame(seeds[a], seeds[b])
    x, y = sa.returns, sb.returns
    holds = x.mean() > y.mean() if strict else x.mean() >= y.mean()
    order = (x, y) if holds else (y, x)
    digits = 2 if is_kitchen(task.split(",")[0]) else 1  # the kitchen's: a success rate
    evidence = f"{NAMES[a]} {_spread(x, digits)} against {NAMES[b]} {_spread(y, digits)}{note}"
    verdict = f"{'holds' if holds else 'does not hold'} ({_separate(*order)})"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def _efficiency(task, baseline, seeds, threshold) -> dict:
    claim = f"DEAR >= 25% more sample-efficient than {NAMES[baseline]}"
    if "dear" not in seeds or baseline not in seeds:
        missing = " and ".join(NAMES[m] for m in ("dear", baseline) if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    d, b = seeds["dear"], seeds[baseline]
    evidence = f"median frames to {threshold:g}: DEAR {_frames(d, threshold)}, "
    evidence += f"{NAMES[baseline]} {_frames(b, threshold)}"
    (d_low, d_high), (b_low, b_high) = d.median_bounds(), b.median_bounds()
    if d_low == d_high and b_low == b_high and b_high > 0:
        evidence += f"; ratio {d_high / b_high:.2f}"
    if b_high == 0:  # the baseline's median seed reached T at its first evaluation
        verdict = "does not hold"
    elif d_high <= EFFICIENCY * b_low:
        verdict = "holds"
    elif d_low > EFFICIENCY * b_high:
        verdict = "does not hold"
    elif math.isinf(d_high) and math.isinf(b_high):
        verdict = "undecided: neither's median seed reaches it"
    else:
        verdict = "undecided: the runs are too short to tell"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def _cosine(task, seeds) -> dict:
    claim = "DEAR's |cos| far below SEAR's"
    if "dear" not in seeds or "sear" not in seeds:
        missing = " and ".join(NAMES[m] for m in ("dear", "sear") if m not in seeds)
        return dict(claim=claim, task=task, evidence="-", verdict=f"no data: no {missing} run")
    dear, sear, note = _at_one_frame(seeds["dear"], seeds["sear"])
    d, s = dear.abs_cos, sear.abs_cos
    if np.isnan(d).any() or np.isnan(s).any():
        return dict(claim=claim, task=task, evidence="-", verdict="no data: logs without |cos|")
    ratio = s.mean() / d.mean()
    evidence = (
        f"DEAR {d.mean():.1e}, SEAR {s.mean():.1e}: {ratio:.1f}x (asked: >= {COS_RATIO:g}x){note}"
    )
    holds = ratio >= COS_RATIO
    order = (s, d) if s.mean() >= d.mean() else (d, s)  # the higher side first
    verdict = f"{'holds' if holds else 'does not hold'} ({_separate(*order)})"
    return dict(claim=claim, task=task, evidence=evidence, verdict=verdict)


def check(workdirs, threshold: float | None = None, at: int | None = None, last: int = 11) -> list:
    """The claims' rows ({claim, task, evidence, verdict}), per task of the runs; threshold
    None: each task's `default_threshold`."""
    found = experiments(workdirs, threshold, at, last)
    rows = []
    for task in dict.fromkeys(t for t, _ in found):
        seeds = {m: s for (t, m), s in found.items() if t == task}
        env_task = task.split(",")[0]  # plot.task_name: the env's name, then its distractions
        target = default_threshold(env_task) if threshold is None else threshold
        rows.append(_greater("DEAR's return >= SEAR's", task, "dear", "sear", seeds, False))
        rows += [_efficiency(task, b, seeds, target) for b in BASELINES]
        if not is_kitchen(env_task):  # the DMC tasks
            rows.append(_greater("TED's return > SEAR's", task, "ted", "sear", seeds, True))
        rows.append(_cosine(task, seeds))
    return rows


def _target(threshold: float | None) -> str:
    if threshold is not None:
        return f"{threshold:g}"
    return f"{DMC_THRESHOLD:g} (the kitchen's: {KITCHEN_THRESHOLD:g}, a success in every episode)"


def claims_table(workdirs, threshold=None, at=None, last=11, out=None) -> tuple[list, str]:
    """Rows and Markdown of the claims; with `out`, also writes out.md and out.json."""
    rows = check(workdirs, threshold, at, last)
    upto = "" if at is None else f" up to {at:,} frames"
    text = (
        f"The paper's claims: returns are each seed's mean over its last {last} evaluations"
        f"{upto}, mean ± population std over seeds; frames to a return of {_target(threshold)}, "
        "the median over seeds (a range, or 'not by', where seeds never reached it); |cos|, "
        "each seed's at its last evaluation, the mean over seeds\n\n"
        + format_table(COLUMNS, [[r[c].replace("|", "\\|") for c in COLUMNS] for r in rows])
        + "\n"
    )
    if out:
        path = pathlib.Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.with_suffix(".md").write_text(text)
        args = dict(threshold=threshold, at=at, last=last, runs=[str(w) for w in workdirs])
        path.with_suffix(".json").write_text(json.dumps(dict(args, claims=rows), indent=1))
    return rows, text
