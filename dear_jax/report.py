"""Command-line reports about the agent and about finished runs.

    python -m dear_jax.report params [--action-dim 6]
    python -m dear_jax.report table RUN [RUN ...] [--threshold T] [--at FRAMES] [--last 11] [--out PREFIX]
    python -m dear_jax.report curves RUN [RUN ...] [--out curves.png] [--band std]
    python -m dear_jax.report claims RUN [RUN ...] [--threshold T] [--at FRAMES] [--last 11] [--out PREFIX]
    python -m dear_jax.report cosines RUN [RUN ...] [--rows R] [--at FRAMES] [--out PREFIX]
    python -m dear_jax.report grid RUN [RUN ...] [--tasks walker cup finger] [--methods dear sear ted drqv2]
        [--seeds 3] [--frames 1000000] [--seeds-per-run 1]
    python -m dear_jax.report evals RUN [RUN ...] [--out PREFIX]

`params` prints the parameter count of every module per method (walker: |A| = 6), computed from
shapes only (jax.eval_shape), so it is instant and allocates nothing.

`table` is the paper's Table II for the given run workdirs (what `run.py` writes), one row per
experiment, beside the paper's figures on walker-walk's rows (docs/method.md; a 1080Ti/3080). Runs of
the same config but for their seeds (other machines, other days: give each its own
--config.seed) are one experiment, their seeds pooled; the row names the runs and their commits
and devices (`sources` in the CSV), and how they evaluated where that differs (evaluation
processes, episodes, interval: settings a resumed run may change):
  params (M)          the run's agent (encoder, actor, critic and its method's heads)
  s / 1000 frames     wall-clock seconds per 1000 frames of one seed, amortised over the seeds
                      trained together (the paper runs one seed per process): "training" from
                      the median train-log rate (rows an evaluation slowed are the exceptions),
                      "with eval" from the whole run's wall clock (summary.json)
  eval frame          the frame of the evaluation read (the last one, or with --at FRAMES the
                      last one up to FRAMES per seed, so that runs stopped at different points
                      compare at one frame); "a-b" where the seeds' differ
  cos(z_A, z_E)       mean cosine between the latent halves on that evaluation's batches
  abs cos(z_A, z_E)   the mean of its magnitude (signs cancel in the mean of the cosine; runs
                      logged before commit f3d5730 have no such column: "-")
  final return        that evaluation's return, mean ± std over seeds (population std, ddof 0)
  mean of the last    each seed's mean return over its last --last evaluations (11 by default:
  evaluations         900k-1M of a 1M-frame run), mean ± std over seeds: steadier than one
                      evaluation, which swings far from the next
  frames to T         first evaluated frame at which a seed's return reaches --threshold, the
                      median over all seeds (a range where seeds stopped short of it leave the
                      median between two frames; "not by F" where the median seed did not reach it
                      by its last evaluation; "k/S reach T" says how many did);
                      without it, a return of 500 on the DMC tasks, in the kitchen a success
                      rate of 1 (every evaluation episode)
It prints Markdown and, with --out PREFIX, writes PREFIX.md and PREFIX.csv. A sweep's run
(`dear_jax/lanes.py`) gives one row per setting.

`claims` checks the paper's claims one by one on the runs' pooled seeds (`dear_jax/claims.py`):
DEAR's return >= SEAR's; DEAR >= 25% more sample-efficient than each baseline; TED's return >
SEAR's on the DMC tasks; DEAR's |cos| far below SEAR's. Each says whether it holds, with the
spread over seeds, or that the runs it needs are missing.

`cosines` sets the cosine's figures side by side, per seed: on the last evaluation's
observations (what `table` reports) and in the training log's last --rows rows, each row the mean
over every update since the row before (its "samples": updates x batch). A signed mean over many
samples cancels wherever the sign is not systematic: it measures a bias between the halves, the
magnitude |cos| how far from orthogonal each sample is.

`grid` says how far the runs have taken the paper's grid (`configs/paper.py:TASK,METHOD`, the
kitchen's too with `--tasks light kettle`; a task with more of paper.py's parts for another
setting, e.g. `--tasks walker,medium-full`, or `walker,beta=10`: a weight ablation's cell, for
the methods that read beta): a run belongs to a cell when its config is the
cell's but for its seeds, envs per seed, dtype and replay store (`GRID_MAY_DIFFER`; `table` and
`claims` keep runs that chose these differently apart, and the grid names such cells). Per cell: the
seeds that trained --frames frames, the runs stopped short and how far (or running: a live
process holds its workdir, and its seeds count as coming), how many seeds are missing; then a
command per stopped run that kept a checkpoint and its replay (its resume: one whose replay was
in memory, `replay.disk` False, would resume on an empty one, so it is not) and per missing seed
that no resume brings (one seed-run, a config.seed no run of the cell used, with the dtype, envs
per seed and replay settings its finished runs all chose, so that it pools with them); last the runs of its
tasks and methods in no cell (sweeps included), each with the field that keeps it out, and how many
runs are of other tasks or methods. `python -m dear_jax.grid` runs
those commands as a queue over GPUs.

`evals` says whether a run's evaluations kept up with its training (`eval_rows`): where one
evaluation (over the run's evaluation processes) takes longer than the training between two, the loop
waits for it; and what its periodic checkpoints cost (each first waits for the evaluations in
flight).

`curves` is the paper's learning-curve figure (`dear_jax/plot.py`): one panel per task, one line
per experiment (per setting of a sweep: the beta-sweep figure from the sweep's run; labelled by
the numbers that set it apart, `lanes.pools`), the mean over its pooled seeds, the spread shaded.
A line runs as far as every one of its seeds has evaluated; where a seed stopped earlier (or is
still training), its legend says where the line stops.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import math
import pathlib
import shlex

import jax
import numpy as np

from dear_jax import claims, lanes, lock, plot
from dear_jax.logger import format_table, read_csv
from dear_jax.update import METHODS, AgentConfig, init_params

MODULES = ("encoder", "actor", "critic", "mask_decoder", "recon_decoder", "ted")


def param_counts(cfg: AgentConfig) -> dict[str, int]:
    shapes = jax.eval_shape(functools.partial(init_params, cfg), jax.random.key(0))
    return {
        name: sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(tree))
        for name, tree in shapes.items()
    }


def params_table(action_dim: int = 6) -> list[tuple[str, dict[str, int]]]:
    rows = [(m, param_counts(AgentConfig(action_dim=action_dim, method=m))) for m in METHODS]
    rows.append(
        (
            "drqv2 (plain encoder)",
            param_counts(AgentConfig(action_dim=action_dim, method="drqv2", encoder="plain")),
        )
    )
    return rows


def format_params_table(rows) -> str:
    header = ["method", *MODULES, "total"]
    lines = [header]
    for method, counts in rows:
        cells = [f"{counts[m]:,}" if m in counts else "-" for m in MODULES]
        lines.append([method, *cells, f"{sum(counts.values()):,}"])
    widths = [max(len(r[i]) for r in lines) for i in range(len(header))]
    fmt = lambda r: "| " + " | ".join(c.rjust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([fmt(lines[0]), sep, *map(fmt, lines[1:])])


# The paper's table (docs/method.md: walker-walk on a 1080Ti/3080, and the cosine metric):
# beside walker-walk's rows alone.
PAPER = {
    "drqv2": {"params_m": 12.86, "s_per_1000": 12.55},
    "sear": {"params_m": 16.21, "s_per_1000": 18.02, "cos": 0.1},
    "ted": {"params_m": 12.87, "s_per_1000": 16.19},
    "dear": {"params_m": 14.09, "s_per_1000": 16.11, "cos": 1e-7},
}
TABLE_COLUMNS = (
    "run",
    "method",
    "task",
    "seeds",
    "params (M)",
    "paper params (M)",
    "s / 1000 frames, training",
    "s / 1000 frames, with eval",
    "paper s / 1000 frames",
    "cos(z_A, z_E)",
    "abs cos(z_A, z_E)",
    "paper cos",
    "eval frame",
    "final return",
    "mean of the last evaluations",
    "frames to threshold",
    "commit, device",
)


def _action_dim(summary: dict, task: str) -> int:
    if "action_dim" in summary:
        return int(summary["action_dim"])
    from envs import dmc, kitchen  # runs written before summaries held it

    tasks = {**dmc.TASKS, **kitchen.TASKS}
    return int(tasks[task].physics_model().nu)


def _last_mean(evals: list[dict], column: str) -> float:
    """Mean over seeds of a column's last evaluation (NaN where a log lacks the column)."""
    return float(np.mean([e[column][-1] if column in e else math.nan for e in evals]))


def _until(evals: dict, frames: int | None, path: pathlib.Path, near: float) -> dict:
    """An eval log's rows up to `frames` per seed (all of them for None), an evaluation up to
    `near` frames past it counted as at it (it starts at the first step at or after its mark)."""
    if not len(evals.get("frame", ())):
        raise ValueError(f"{path} has no evaluation yet (the first is written at frame 0)")
    if frames is None:
        return evals
    keep = evals["frame"] <= frames + near
    if not keep.any():
        raise ValueError(f"{path} has no evaluation at or before {frames:,} frames")
    return {name: column[keep] for name, column in evals.items()}


def _run_files(workdir: pathlib.Path) -> tuple[dict, dict]:
    """A run workdir's config.json and summary.json."""
    for name in ("config.json", "summary.json"):
        if not (workdir / name).is_file():
            raise lanes.not_a_run(workdir, name)
    return tuple(json.loads((workdir / n).read_text()) for n in ("config.json", "summary.json"))


def _source(workdir: pathlib.Path, config: dict, summary: dict, seeds: int) -> dict:
    """Where a pooled row's seeds come from: the workdir, the code and machine that ran it, and
    how it evaluated (settings a run may change on resuming, so runs that differ in them pool)."""
    made = summary.get("provenance", {})
    return {
        "evaluation": {
            "num_eval_episodes": config.get("num_eval_episodes"),
            "eval_every_frames": config.get("eval_every_frames"),
            "eval_processes": summary.get("eval_processes", 1),  # before the field: one
        },
        # runs that trained side by side on its GPU (`summary.RUNS_PER_GPU_ENV`; before the field:
        # the run alone)
        "runs_per_gpu": summary.get("runs_per_gpu", 1),
        "workdir": str(workdir),
        "seeds": seeds,
        "frames_per_seed": summary["frames_per_seed"],
        "stopped": summary.get("stopped"),
        "commit": made.get("commit", "?"),
        "device": made.get("device_kind", summary.get("device", "?")),
        "jax": made.get("jax", "?"),
    }


def run_rows(workdir, threshold: float | None, at: int | None = None, last: int = 11) -> list[dict]:
    """Table II's rows for one run workdir: one, or one per setting of a sweep."""
    return pooled_rows([workdir], threshold, at, last)


def pooled_rows(
    workdirs, threshold: float | None, at: int | None = None, last: int = 11
) -> list[dict]:
    """Table II's numbers for run workdirs (config.json, summary.json, their lanes' CSVs): one
    row per experiment and setting, its seeds pooled over the workdirs that ran them
    (`plot.pools`); `sources` says which workdir gave how many seeds, with its commit, device
    and jax version. With `at`, the returns, cosines and frames to the threshold are those of
    the evaluations up to `at` frames per seed (runs stopped at different points compare at the
    same frame). Beside the final return, each seed's mean over its last `last` evaluations (one
    evaluation swings far from the next), then their mean and std over seeds. A threshold of
    None is each task's `claims.default_threshold`."""
    if last < 1:
        raise ValueError(f"last must be at least 1 evaluation, got {last}")
    if at is not None and at < 0:
        raise ValueError(f"at must be a frame >= 0, got {at}")
    workdirs = [pathlib.Path(w) for w in workdirs]
    files = {w: _run_files(w) for w in workdirs}
    rows = []
    for pool in plot.pools(workdirs):
        config = pool.config
        agent = config["agent"]
        task = config["env"]["task"]
        target = claims.default_threshold(task) if threshold is None else threshold
        first = files[pool.workdirs[0]][1]
        cfg = AgentConfig(
            action_dim=_action_dim(first, task),
            method=agent["method"],
            encoder=agent["encoder"],
            latent_dim=agent["latent_dim"],
            feature_dim=agent["feature_dim"],
            hidden_dim=agent["hidden_dim"],
        )
        training, walls, frames, sources = [], 0.0, 0, []
        for workdir in pool.workdirs:
            summary = files[workdir][1]
            groups = lanes.groups(workdir)
            # Rates are of all of a run's lanes together (each log row's fps; its wall clock).
            fps = read_csv(next(iter(groups.values()))[0] / "train.csv")["fps"]
            fps = fps[np.isfinite(fps)]
            if fps.size:
                training.append(1000.0 / np.median(fps))
            walls += summary["wall_s"]
            frames += summary["frames_per_seed"] * sum(map(len, groups.values()))
            mine = sum(w == workdir for w, _ in pool.seeds)
            sources.append(_source(workdir, files[workdir][0], summary, mine))
        dirs = [d for _, d in pool.seeds]
        near = plot.slack(config)
        evals = [_until(read_csv(d / "eval.csv"), at, d / "eval.csv", near) for d in dirs]
        finals = np.array([e["episode_return"][-1] for e in evals])
        lasts = np.array([e["episode_return"][-last:].mean() for e in evals])
        # a seed with fewer than `last` evaluations averages all it has (its frame-0 one too)
        averaged = min(len(e["episode_return"][-last:]) for e in evals)
        frames_to = []  # inf: a seed that never reached the threshold
        for e in evals:
            hit = np.nonzero(e["episode_return"] >= target)[0]
            frames_to.append(e["frame"][hit[0]] if hit.size else math.inf)
        by, median_to = claims.median_frames_to(frames_to, [e["frame"][-1] for e in evals])
        # A run stopped before its end (summary "stopped") is reported as far as it got.
        names = [
            f"{s['workdir'].rsplit('/', 1)[-1]}"
            + (f" ({s['seeds']})" if len(sources) > 1 else "")
            + (f" (stopped at {s['frames_per_seed']:,} frames)" if s["stopped"] else "")
            for s in sources
        ]
        # Pooled runs that evaluated differently (each seed's returns come from its own run's).
        differ = {
            k: "/".join(dict.fromkeys(str(s["evaluation"][k]) for s in sources))
            for k in sources[0]["evaluation"]
        }
        differ = "; ".join(f"{k} {v}" for k, v in differ.items() if "/" in v)
        # and pooled runs paced beside others on their GPU and alone (the s / 1000 frames columns)
        sharing = "/".join(dict.fromkeys(str(s["runs_per_gpu"]) for s in sources))
        rows.append(
            {
                "run": f"{' + '.join(names)} {pool.label}".strip()
                + (f" (evaluations differ: {differ})" if differ else "")
                + (f" (runs per GPU differ: {sharing})" if "/" in sharing else ""),
                "method": agent["method"],
                "task": plot.task_name(config),
                "seeds": len(dirs),
                "params_m": sum(param_counts(cfg).values()) / 1e6,
                "s_per_1000_training": float(np.median(training)) if training else math.nan,
                "s_per_1000_with_eval": 1000.0 * walls / frames if frames else math.nan,
                "cos": _last_mean(evals, "cos_agent_env"),
                "abs_cos": _last_mean(evals, "abs_cos_agent_env"),
                "eval_frame_min": int(min(e["frame"][-1] for e in evals)),
                "eval_frame": int(max(e["frame"][-1] for e in evals)),
                "final_return_mean": float(finals.mean()),
                "final_return_std": float(finals.std()),
                "last_return_mean": float(lasts.mean()),
                "last_return_std": float(lasts.std()),
                "last": last,
                "last_fewest": averaged,  # the fewest evaluations a seed's mean averages
                # the median seed's (inf: it did not reach it by frames_to_threshold_lower)
                "frames_to_threshold": median_to,
                "frames_to_threshold_lower": by,
                "seeds_reaching_threshold": int(np.isfinite(frames_to).sum()),
                "threshold": target,
                "code": ", ".join(
                    dict.fromkeys(f"{s['commit'][:7]} {s['device']}" for s in sources)
                ),
                "sources": json.dumps(sources),
            }
        )
    return rows


def _cells(r: dict) -> list:
    paper = PAPER.get(r["method"], {}) if r["task"].startswith("walker-walk") else {}
    fmt = lambda x, f: "-" if x is None or not np.isfinite(x) else format(x, f)  # noqa: E731
    reached = f"{r['seeds_reaching_threshold']}/{r['seeds']} reach {r['threshold']:g}"
    ret = ".2f" if r["task"].startswith("kitchen") else ".1f"  # the kitchen's: a success rate
    return [
        r["run"],
        r["method"],
        r["task"],
        r["seeds"],
        fmt(r["params_m"], ".2f"),
        fmt(paper.get("params_m"), ".2f"),
        fmt(r["s_per_1000_training"], ".2f"),
        fmt(r["s_per_1000_with_eval"], ".2f"),
        fmt(paper.get("s_per_1000"), ".2f"),
        fmt(r["cos"], ".2e"),
        fmt(r["abs_cos"], ".2e"),
        fmt(paper.get("cos"), ".0e"),
        _frames(r["eval_frame_min"], r["eval_frame"]),
        f"{r['final_return_mean']:{ret}} ± {r['final_return_std']:{ret}}",
        f"{r['last_return_mean']:{ret}} ± {r['last_return_std']:{ret}}"
        + (f" (a seed's over {r['last_fewest']})" if r["last_fewest"] < r["last"] else ""),
        _frames_to(r["frames_to_threshold"], r["frames_to_threshold_lower"]) + f" ({reached})",
        r["code"],
    ]


def _frames_to(median: float, lower: float) -> str:
    """The median seed's frames to the threshold (`claims.median_frames_to`'s bounds): a frame,
    a range where a seed stopped short of it leaves the median between two, or the frame it had
    not reached it by."""
    if not np.isfinite(median):
        return f"not by {lower:,.0f}"
    return f"{median:,.0f}" if lower >= median else f"{lower:,.0f}-{median:,.0f}"


def _frames(low: int, high: int) -> str:
    return f"{high:,}" if low == high else f"{low:,}-{high:,}"


def runs_table(
    workdirs, threshold: float | None, out: str | None = None, at: int | None = None, last: int = 11
) -> tuple[list[dict], str]:
    """Rows and the Markdown text of Table II; with `out`, also writes out.md and out.csv.
    threshold None: each task's `claims.default_threshold`."""
    rows = pooled_rows(workdirs, threshold, at, last)
    when = "the last evaluation" if at is None else f"the last evaluation up to {at:,} frames"
    text = (
        f"Table II: {len(rows)} experiment(s), each with its seeds pooled over the runs named; "
        "s / 1000 frames per seed amortised over the seeds "
        f"trained together; returns and cosines of {when} (return: mean ± population std over "
        f"seeds; beside it each seed's mean over its last {last} evaluations, mean ± std over "
        "seeds); frames to threshold: the first evaluation whose return reaches it, the median "
        "over seeds (a seed that never does took longer than its last evaluation: where that "
        "leaves the median between two frames, both are given; 'not by F' where it may lie past "
        "every seed's)\n\n" + format_table(TABLE_COLUMNS, [_cells(r) for r in rows]) + "\n"
    )
    if out:
        path = pathlib.Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.with_suffix(".md").write_text(text)
        with path.with_suffix(".csv").open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return rows, text


COSINE_COLUMNS = (
    "seed",
    "method",
    "eval frame",
    "eval abs cos",
    "eval cos",
    "train frames",
    "train abs cos",
    "train cos",
    "train cos, median abs per row",
    "samples per row",
)


def cosine_rows(workdirs, rows: int = 20, at: int | None = None) -> list[dict]:
    """Per seed of the runs (pooled as `table` pools them): the cosine between the latent halves
    at the last evaluation (up to `at` frames per seed) and over the training log's last `rows`
    rows up to that frame: the mean of the rows' |cos| and signed cos, the median magnitude of
    a row's signed cos, and how many samples a row averages (updates x batch)."""
    if rows < 1:
        raise ValueError(f"rows={rows}: give at least 1 training-log row")
    out = []
    for pool in plot.pools([pathlib.Path(w) for w in workdirs]):
        batch = pool.config["agent"]["batch_size"]
        for workdir, seed_dir in pool.seeds:
            evals = _until(
                read_csv(seed_dir / "eval.csv"), at, seed_dir / "eval.csv", plot.slack(pool.config)
            )
            train = read_csv(seed_dir / "train.csv")
            needed = ("abs_cos_agent_env", "cos_agent_env", "updates")
            missing = [name for name in needed if name not in train]
            if missing:
                raise ValueError(
                    f"{seed_dir / 'train.csv'} has no {', '.join(missing)} column(s) "
                    "(a log written before they were)"
                )
            # The rows with metrics (a row of episode returns alone ran no update since the
            # row before), up to the evaluation read.
            metrics = np.isfinite(train["cos_agent_env"]) & (train["frame"] <= evals["frame"][-1])
            keep = np.nonzero(metrics)[0][-(rows + 1) :]
            if keep.size < 2:
                raise ValueError(
                    f"{seed_dir / 'train.csv'}: fewer than 2 rows of metrics up to frame "
                    f"{int(evals['frame'][-1]):,} (a row's samples are the updates since the last)"
                )
            samples = np.diff(train["updates"][keep]) * batch
            keep = keep[1:]  # each row's samples: the updates since the row before
            signed = train["cos_agent_env"][keep]
            out.append(
                {
                    "seed": f"{workdir.name}/{seed_dir.name}",  # a lane's folder names its setting
                    "method": pool.config["agent"]["method"],
                    "eval_frame": int(evals["frame"][-1]),
                    "eval_abs_cos": float(evals.get("abs_cos_agent_env", [math.nan])[-1]),
                    "eval_cos": float(evals.get("cos_agent_env", [math.nan])[-1]),
                    "train_frames": "-".join(f"{int(train['frame'][i]):,}" for i in keep[[0, -1]]),
                    "train_abs_cos": float(np.mean(train["abs_cos_agent_env"][keep])),
                    "train_cos": float(np.mean(signed)),
                    "train_cos_row_median_abs": float(np.median(np.abs(signed))),
                    "samples_per_row": int(np.median(samples)),
                }
            )
    return out


def cosines_table(workdirs, rows: int = 20, at: int | None = None) -> tuple[list[dict], str]:
    """The rows of `cosine_rows` and their Markdown table."""
    found = cosine_rows(workdirs, rows, at)
    cells = [
        [
            r["seed"],
            r["method"],
            f"{r['eval_frame']:,}",
            *(f"{r[k]:.2e}" for k in ("eval_abs_cos", "eval_cos")),
            r["train_frames"],
            *(f"{r[k]:.2e}" for k in ("train_abs_cos", "train_cos", "train_cos_row_median_abs")),
            f"{r['samples_per_row']:,}",
        ]
        for r in found
    ]
    text = (
        f"cos(z_A, z_E) per seed: on the last evaluation's observations, and in the last {rows} "
        "training-log rows (means over the rows; each row averages its samples)\n\n"
        + format_table(COSINE_COLUMNS, cells)
        + "\n"
    )
    return found, text


EVALS_COLUMNS = (
    "run",
    "method",
    "task",
    "lanes",
    "eval processes",
    "evaluation s",
    "s between evaluations",
    "s of training between",
    "loop waited for evaluations",
    "rows with a checkpoint, beyond the training's pace",
)


def _holding(since: np.ndarray, logged: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Which train-log rows hold something the loop did at one of `frames`: a row logged at
    frame F, after the row at `since`, holds what happened at frames since <= f < F (the loop
    logs a row before it evaluates or checkpoints at that row's own frame)."""
    frames = np.sort(frames)
    after = np.searchsorted(frames, since)  # the first of `frames` at or after a row's start
    return (after < frames.size) & (np.append(frames, np.inf)[after] < logged)


def eval_rows(workdirs) -> list[dict]:
    """Whether a run's evaluations kept up with its training, from its logs (the first lane's):
    the median time an evaluation took (`eval_s`, from its start in its thread: with the wait
    for its copy of the parameters); the median time between two evaluations falling due
    (`wall_s`; intervals of eval_every_frames only: the closing evaluation's is shorter); the
    time the training takes for eval_every_frames at the median rate of the train-log rows
    that hold no evaluation's start (the loop starts one after logging the row of its frame,
    so a row holds the starts at frames from the row before it, inclusive, to its own); and the
    time the loop was held up by evaluations before going on (`loop_wait_s`, summed over the
    rows that log it, and its share of the run's wall clock; NaN for runs logged before the
    column; a checkpoint's wait for the evaluations in flight is not in it). Evaluations queue
    (dear_jax/evaluations.py): where they fall behind, the loop waits, and the time between two
    falling due outgrows the training's. Last, the time the train-log rows that hold a periodic
    checkpoint (checkpoint_every_frames; the save waits for the evaluations in flight) took
    beyond what the training's rate gives their frames, summed, and its share of the wall clock."""
    rows = []
    for workdir in map(pathlib.Path, workdirs):
        config, summary = _run_files(workdir)
        groups = lanes.groups(workdir)
        first = next(iter(groups.values()))[0]
        every = config["eval_every_frames"]
        evals = read_csv(first / "eval.csv")
        train = read_csv(first / "train.csv")
        logged, fps = train["frame"], train["fps"]  # fps: env frames/s of all lanes together
        since = np.concatenate([[0.0], logged[:-1]])
        num_lanes = sum(map(len, groups.values()))
        clean = fps[~_holding(since, logged, evals["frame"]) & np.isfinite(fps)]
        rate = np.median(clean) if clean.size else math.nan  # env frames/s, all lanes
        train_s = every * num_lanes / rate
        ckpt_every = config["checkpoint_every_frames"]
        saves = np.arange(ckpt_every, logged.max(initial=0) + 1, ckpt_every) if ckpt_every else []
        held = _holding(since, logged, np.asarray(saves, float)) & np.isfinite(fps)
        span = (logged - since)[held] * num_lanes
        ckpt_s = float(np.sum(span / fps[held] - span / rate))
        later = evals["frame"] > 0  # the first evaluation runs beside the compile
        starts, frames = evals["wall_s"][later], evals["frame"][later]
        whole = np.diff(frames) >= 0.9 * every
        between = np.diff(starts)[whole]
        waits = evals.get("loop_wait_s", np.array([math.nan]))
        waited = float(np.nansum(waits)) if np.isfinite(waits).any() else math.nan
        wall = summary["wall_s"]
        rows.append(
            {
                "run": workdir.name,
                "method": config["agent"]["method"],
                "task": plot.task_name(config),
                "lanes": num_lanes,
                # the summary's count: the config's 0 is resolved there (1 before the field)
                "eval_processes": summary.get("eval_processes", config.get("eval_processes", 1)),
                "eval_s": float(np.median(evals["eval_s"][later])) if later.any() else math.nan,
                "between_s": float(np.median(between)) if between.size else math.nan,
                "train_s": float(train_s),
                "checkpoint_excess_s": ckpt_s,
                "checkpoint_excess_share": ckpt_s / wall if wall else math.nan,
                "loop_wait_s": waited,
                "loop_wait_share": waited / wall if wall else math.nan,
            }
        )
    return rows


def evals_table(workdirs, out: str | None = None) -> tuple[list[dict], str]:
    """The rows of `eval_rows` and their Markdown table; with `out`, also writes out.md."""
    rows = eval_rows(workdirs)
    cells = [
        [
            r["run"],
            r["method"],
            r["task"],
            r["lanes"],
            r["eval_processes"],
            f"{r['eval_s']:.1f}",
            f"{r['between_s']:.1f}",
            f"{r['train_s']:.1f}",
            "-"
            if math.isnan(r["loop_wait_s"])
            else f"{r['loop_wait_s']:.0f} s ({100 * r['loop_wait_share']:.0f}%)",
            f"{r['checkpoint_excess_s']:.0f} s ({100 * r['checkpoint_excess_share']:.0f}%)",
        ]
        for r in rows
    ]
    text = (
        "Evaluations against the training between them (medians; s of training: eval_every_frames "
        "at the median rate of the train-log rows that hold no evaluation's start; the loop's waits for evaluations to end, in all and as a "
        "share of the run's wall clock, '-' where not logged; the same for the log rows that hold a "
        "checkpoint, beyond what the training's rate gives their frames)\n\n"
        + format_table(EVALS_COLUMNS, cells)
        + "\n"
    )
    if out:
        path = pathlib.Path(out).with_suffix(".md")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return rows, text


# What a seed-run of a grid cell may set otherwise than configs/paper.py, besides what any resume
# may change (experiment.RESUMABLE_CHANGES): how many seeds and envs it steps, its dtype, its
# replay's size, warm-up and place (not its sampling). Every other field is the cell's.
GRID_MAY_DIFFER = (
    "seed",
    "seeds",
    "envs_per_seed",
    "agent.compute_dtype",
    "replay.capacity",
    "replay.seed_frames",
    "replay.disk",
    "replay.chunk_entries",
)


SEEDS_PER_RUN_HELP = "missing seeds a new seed-run trains side by side, as lanes of one process"


def positive_int(text: str) -> int:
    """argparse's type for a count of seeds or frames: an int >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a whole number >= 1, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


TASKS_HELP = (
    "TASK or TASK,DIFFICULTY[,MASK][,WEIGHT=VALUE...] (configs/paper.py's parts), e.g. "
    "walker,medium-full or walker,beta=10 (cells of the methods that read the weight)"
)


def grid_run_fields() -> tuple[str, ...]:
    """The fields (a name, or a prefix ending in ".") a seed-run of the grid chooses for itself
    and keeps when it resumes: GRID_MAY_DIFFER and the resumable ones (experiment.
    RESUMABLE_CHANGES) but its length, which the grid's frames set."""
    from dear_jax.experiment import RESUMABLE_CHANGES

    return (*GRID_MAY_DIFFER, *(f for f in RESUMABLE_CHANGES if f != "total_frames"))


def training_pace(workdir: pathlib.Path, config: dict, summary: dict) -> tuple[float, float] | None:
    """A finished run's wall-clock seconds per frame per seed, as (its training's own pace, its
    periodic checkpoints' share): `eval_rows`' train_s / eval_every_frames and
    checkpoint_excess_s / frames, leaving out its waits for evaluations that outlast the
    training between two; without readable logs, (its summary's wall clock per frame, 0), the
    checkpoints inside the first; else None."""
    try:
        row = eval_rows([workdir])[0]
        pace = row["train_s"] / config["eval_every_frames"]
        checkpoints = row["checkpoint_excess_s"] / summary["frames_per_seed"]
    except (OSError, ValueError, KeyError, IndexError, StopIteration, ZeroDivisionError):
        pace = checkpoints = math.nan
    if math.isfinite(pace) and math.isfinite(checkpoints):
        return pace, checkpoints
    if summary.get("wall_s") and summary.get("frames_per_seed"):
        return summary["wall_s"] / summary["frames_per_seed"], 0.0
    return None


def _first_difference(fields: dict, ref: dict) -> str | None:
    """The first field (sorted) in which a run's flattened config differs from a cell's."""
    from dear_jax.experiment import RESUMABLE_CHANGES

    for key in sorted(set(fields) | set(ref)):
        if key in RESUMABLE_CHANGES or key.startswith(GRID_MAY_DIFFER):
            continue
        if fields.get(key) != ref.get(key):
            return f"{key}={fields.get(key)!r} (the cell's: {ref.get(key)!r})"
    return None


def grid_rows(workdirs, tasks, methods, seeds: int = 3, frames: int = 1_000_000, taken=()) -> dict:
    """The cells (`configs/paper.py:TASK,METHOD`; a task given with more of paper.py's parts, e.g.
    "walker,medium-full" or "walker,beta=10": `configs/paper.py:TASK,METHOD,MORE`, for the methods
    that read its weights) of the paper's grid as far as `workdirs` trained them (see the module
    docstring): {"cells": a row per cell,
    "outside": the runs of the grid's tasks and methods in no cell, each with the field that
    keeps it out (sweeps too), "elsewhere": the runs of other tasks or methods}. Two tasks of one
    setting (e.g. "walker" and "walker,medium", paper.py's default) are refused. A cell's
    "resume" lists the stopped runs that kept a checkpoint and bring seeds it misses (furthest
    first), "next_seeds" the config.seed of each seed-run still to start: one no run of the cell
    used, whose workdir name (the cell's "name", then _sSEED) is not in `taken`."""
    from configs import paper
    from configs.base import get_config
    from dear_jax.experiment import ADDED_FIELDS, REMOVED_FIELDS, RESUMABLE_CHANGES

    kept = grid_run_fields()  # a resume restarts a run with what it chose
    # A field a run's config lacks: what the code did before the field, else today's default.
    defaults = {**lanes.flatten(get_config().to_dict()), **ADDED_FIELDS}
    cells = {}
    for given in tasks:  # TASK or TASK,DIFFICULTY[,MASK][,WEIGHT=VALUE...]
        name, *setting = (part.strip() for part in given.split(","))
        task = ",".join([name, *setting])
        weights = [part.split("=")[0].strip() for part in setting if "=" in part]
        readers = [m for m in methods if all(lanes.reads(m, w) for w in weights)]
        if not readers:
            read = ", ".join(weights)
            raise ValueError(f"task {given!r}: none of {', '.join(methods)} reads {read}")
        for method in readers:
            spec = ",".join([name, method, *setting])
            ref = lanes.flatten(paper.get_config(spec).to_dict())
            twin = next((c["task"] for c in cells.values() if c["ref"] == ref), None)
            if twin is not None:
                raise ValueError(f"tasks {twin!r} and {given!r} are one setting: give it once")
            cells[task, method] = {
                "task": task,
                "method": method,
                "spec": spec,
                "name": "_".join([name, *setting, method]),
                "ref": ref,
                "seeds": set(),  # (config.seed, lane seed) of the seeds that reached `frames`
                "done": [],
                "short": [],
                "stopped": [],  # (frames reached, the seeds it brings, its resume's arguments)
                "coming": set(),  # the seeds of its runs that train now
                "used": set(),
                "paces": [],  # (lanes, *`training_pace`) of the runs that reached `frames`
                "chosen": {},  # field -> the values its finished runs chose (GRID_MAY_DIFFER's)
            }
    outside, elsewhere = [], []
    # (env.task, method) -> (lanes, *`training_pace`) of its runs in any setting (sweeps aside)
    # that reached `frames`: the length of a cell's seed-runs where the cell has none of its own
    related: dict[tuple[str, str], list] = {}
    for workdir in dict.fromkeys(pathlib.Path(w).resolve() for w in workdirs):
        name = f"{workdir.parent.name}/{workdir.name}"
        path = workdir / "config.json"
        if not path.is_file():
            raise lanes.not_a_run(workdir)
        config = json.loads(path.read_text())
        fields = {**defaults, **lanes.flatten(config)}
        for key in REMOVED_FIELDS:  # no resume command may name them
            fields.pop(key, None)
        same = [c for c in cells.values() if c["ref"]["env.task"] == fields["env.task"]]
        same = [c for c in same if c["method"] == fields["agent.method"]]
        if not same:
            elsewhere.append(name)
            continue
        if set(lanes.groups(workdir)) != {""}:
            outside.append(f"{name}: a sweep (sweep.*)")
            continue
        # The cell whose config it has; else it is named with its first difference from the
        # first cell of its task and method (the paper's setting where the grid has it).
        cell = next((c for c in same if _first_difference(fields, c["ref"]) is None), None)
        summary_path = workdir / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
        reached = summary.get("frames_per_seed")
        pace = None
        # A job's length goes by runs that trained alone on their GPU (`grid.shared_gpu_lengths`
        # bounds those of jobs that share one)
        if reached is not None and reached >= frames and summary.get("runs_per_gpu", 1) == 1:
            pace = training_pace(workdir, config, summary)
            if pace is not None:
                key = (fields["env.task"], fields["agent.method"])
                related.setdefault(key, []).append((config["seeds"], *pace))
        if cell is None:
            outside.append(f"{name}: {_first_difference(fields, same[0]['ref'])}")
            continue
        seed = config.get("seed", 0)
        cell["used"].add(seed)
        # Stopped at its last frame, in its last iteration or its closing evaluation, which it
        # has not run (train._finished): resumed where it kept checkpoints (it runs that
        # evaluation then); without them, done, its last evaluation the one before.
        unfinished = (
            bool(summary.get("stopped"))
            and (reached or 0) >= config.get("total_frames", math.inf)
            and (workdir / "checkpoints").is_dir()
        )
        if reached is not None and reached >= frames and not unfinished:
            cell["done"].append(name)
            for k in fields:
                if k.startswith(GRID_MAY_DIFFER) and k not in ("seed", "seeds", *RESUMABLE_CHANGES):
                    cell["chosen"].setdefault(k, set()).add(json.dumps(fields[k]))
            if pace is not None:
                cell["paces"].append((config["seeds"], *pace))
            # A seed is (config.seed, lane seed): one trained to the end twice counts once.
            cell["seeds"].update((seed, s) for s in range(config["seeds"]))
            continue
        running = lock.held(workdir)  # a run in it now: its seeds are coming, not to resume
        brings = {(seed, s) for s in range(config["seeds"])}
        state = "running" if running else "no summary" if reached is None else f"{reached:,}"
        state += ", before its closing evaluation" if not running and unfinished else ""
        # A checkpoint without its replay (replay.disk False) would resume on an empty replay:
        # another seed's learning, so such a run is not resumed (unless all it has left is its
        # closing evaluation).
        closing_only = unfinished and reached >= frames
        resumable = (workdir / "checkpoints").is_dir() and (
            fields.get("replay.disk", True) or closing_only
        )
        if not running and (workdir / "checkpoints").is_dir() and not resumable:
            state += ", its replay not kept"
        cell["short"].append(f"{name} ({state})")
        if running:
            cell["coming"] |= brings
        elif resumable:  # resumed as it was started
            own = [
                f"--config.{k}={fields[k]}"
                for k in sorted(fields)
                if k.startswith(kept) and fields[k] != cell["ref"].get(k)
            ]
            cell["stopped"].append((reached or 0, brings, [*own, "--workdir", str(workdir)]))
    rows = []
    for cell in cells.values():
        missing = max(0, seeds - len(cell["seeds"]))
        resume, brought = [], cell["seeds"] | cell["coming"]
        for _, brings, args in sorted(cell["stopped"], key=lambda s: -s[0]):
            if len(brought) - len(cell["seeds"]) < missing and brings - brought:
                resume.append(args)
                brought |= brings
        new = max(0, missing - (len(brought) - len(cell["seeds"])))
        name = f"{cell['name']}_s{{}}"
        free = (n for n in range(10**6) if n not in cell["used"] and name.format(n) not in taken)
        rows.append(
            {
                "task": cell["task"],
                "method": cell["method"],
                "spec": cell["spec"],
                "name": cell["name"],
                "seeds_done": len(cell["seeds"]),
                "done": cell["done"],
                "short": cell["short"],
                "resume": resume,
                "missing": missing,
                "next_seeds": [next(free) for _ in range(new)],
                "total_frames": cell["ref"]["total_frames"],
                "paces": cell["paces"],
                # without its own: those of its task and method in other settings
                "related_paces": related.get((cell["ref"]["env.task"], cell["method"]), []),
                # fields its runs chose differently: `report table` and `claims` keep them apart
                "mixed": {k: sorted(v) for k, v in sorted(cell["chosen"].items()) if len(v) > 1},
                # fields every finished run chose alike, other than the cell's config: its new
                # seed-runs choose them too, so that they pool with those runs
                "agreed": {
                    k: value
                    for k, values in sorted(cell["chosen"].items())
                    if len(values) == 1
                    for value in map(json.loads, values)
                    if value != cell["ref"].get(k)
                },
            }
        )
    return {"cells": rows, "outside": outside, "elsewhere": elsewhere}


def _is_zero(text: str) -> bool:
    """Whether a command-line integer (as Python reads one: 0, 00, 0_0, 0x0) is zero."""
    try:
        return int(text.strip(), 0) == 0
    except ValueError:
        return False


@dataclasses.dataclass(frozen=True)
class Job:
    """A seed-run of the grid: its workdir's name, `run.py`'s arguments and, for a new seed-run,
    the seconds it should take (`grid_jobs`; None: no finished run of its cell or of its task
    and method to go by), `at_most` where they are a bound from runs of other lane counts."""

    name: str
    args: tuple[str, ...]
    seconds: float | None = None
    at_most: bool = False


def grid_jobs(
    grid: dict, frames: int, root: str = "runs", overrides=(), seeds_per_run: int = 1
) -> list[Job]:
    """The runs that complete `grid` (`grid_rows`) to `frames` frames per seed: first the stopped
    runs that kept a checkpoint and bring missing seeds (resumed in their workdirs), then the
    seed-runs of the missing seeds that no resume brings, in ROOT/TASK_METHOD_sSEED (a task given
    with more parts: those too, e.g. walker_medium-full_dear_s0), task by task, the task's methods
    taking turns (a queue stopped part way leaves a task's methods with seeds alike). A seed-run trains
    `seeds_per_run` of a cell's missing seeds side by side (lanes of one process; the last of a
    cell the rest), from a config.seed no run of the cell used, with the settings every finished
    run of the cell chose alike (`grid_rows`' "agreed": dtype, envs per seed, replay), so that
    it pools with them. `overrides`: more `--config.FIELD=VALUE` arguments for the new
    seed-runs (a field they name is theirs, not the agreed value). Job names are unique (suffixes _1,
    _2, ... where resumed workdirs share a name). A new seed-run's `seconds`: `frames` at the
    median `training_pace` of the cell's runs of as many lanes that reached the grid's frames
    alone on their GPU (whatever their devices; start-up and the closing evaluation not in it;
    runs that trained beside others, summary "runs_per_gpu" > 1, not counted), their periodic
    checkpoints' share left out where `overrides` set checkpoint_every_frames=0; a cell without
    such runs goes by those of its task and method in other settings, whatever differs (meant for
    the full suite's cell and the weight ablations', whose work is the paper setting's). Without
    runs of as many lanes either, a bound (`at_most`) from those of other lane counts, the
    smallest over counts: K lanes take no longer than a run of more lanes, nor than K / W times
    a run of W lanes (lanes share the device's work, so they train at least as fast together)."""
    if seeds_per_run < 1:
        raise ValueError(f"seeds per run must be at least 1, got {seeds_per_run}")
    cells = grid["cells"]

    def spec(r):
        return ("--config", f"configs/paper.py:{r['spec']}")

    def length(r):
        return (f"--config.total_frames={frames}",) if frames != r["total_frames"] else ()

    given = {o.partition("=")[0] for o in overrides}

    def agreed(r):  # the settings the cell's finished runs share, where overrides do not say
        flags = (f"--config.{k}={v}" for k, v in r.get("agreed", {}).items())
        return tuple(f for f in flags if f.partition("=")[0] not in given)

    def runs(r):  # (config.seed, lanes) of each new seed-run of cell r
        new = len(r["next_seeds"])
        return [
            (r["next_seeds"][j], min(seeds_per_run, new - j * seeds_per_run))
            for j in range(-(-new // seeds_per_run))
        ]

    # Whether the new seed-runs save periodic checkpoints (the last override of the field wins)
    every = [
        o.partition("=")[2] for o in overrides if o.startswith("--config.checkpoint_every_frames=")
    ]
    saves = not every or not _is_zero(every[-1])

    def length_of(paces, lanes: int) -> float | None:  # a seed-run's seconds by these paces
        paces = [p + (c if saves else 0.0) for width, p, c in paces if width == lanes]
        return float(np.median(paces)) * frames if paces else None

    def bound_of(paces, lanes: int) -> float | None:  # at most, by runs of other lane counts
        widths = {width for width, *_ in paces}
        bounds = [length_of(paces, w) * max(1.0, lanes / w) for w in widths]
        return min(bounds) if bounds else None

    def estimate(r, lanes: int) -> tuple[float | None, bool]:  # (seconds, whether at most)
        for of, at_most in ((length_of, False), (bound_of, True)):
            for paces in (r["paces"], r["related_paces"]):
                seconds = of(paces, lanes)
                if seconds is not None:
                    return seconds, at_most
        return None, False

    jobs = [
        Job(pathlib.Path(args[-1]).name, (*spec(r), *length(r), *args))
        for r in cells
        for args in r["resume"]
    ]
    for task in dict.fromkeys(r["task"] for r in cells):
        row = [(r, runs(r)) for r in cells if r["task"] == task]
        for k in range(max(len(new) for _, new in row)):
            for r, new in (x for x in row if k < len(x[1])):
                n, count = new[k]
                name = f"{r['name']}_s{n}"
                seed = (f"--config.seed={n}", f"--config.seeds={count}")
                workdir = ("--workdir", f"{root}/{name}")
                args = (*spec(r), *seed, *length(r), *agreed(r), *overrides, *workdir)
                jobs.append(Job(name, args, *estimate(r, count)))
    names = [job.name for job in jobs]  # resumed workdirs of one name in several folders
    return [
        dataclasses.replace(job, name=f"{job.name}_{names[:i].count(job.name) + 1}")
        if names.count(job.name) > 1
        else job
        for i, job in enumerate(jobs)
    ]


def grid_table(
    workdirs,
    tasks,
    methods,
    seeds: int = 3,
    frames: int = 1_000_000,
    seeds_per_run: int = 1,
    root: str = "runs",
) -> str:
    grid = grid_rows(workdirs, tasks, methods, seeds, frames)
    rows = grid["cells"]
    table = format_table(
        ["task", "method", f"seeds at {frames:,}", "runs", "stopped short (frames)", "missing"],
        [
            [
                r["task"],
                r["method"],
                r["seeds_done"],
                ", ".join(r["done"]) or "-",
                ", ".join(r["short"]) or "-",
                r["missing"],
            ]
            for r in rows
        ],
    )
    lines = [f"The paper's grid at {frames:,} frames per seed, {seeds} seeds per cell", "", table]
    jobs = grid_jobs(grid, frames, root, seeds_per_run=seeds_per_run)
    commands = [f"python run.py {shlex.join(job.args)}" for job in jobs]
    if commands:
        lines += [
            "",
            "Resume the stopped runs that kept a checkpoint, then start the missing seeds:",
        ]
        lines += commands
    mixed = [
        f"{r['task']} {r['method']}: "
        + "; ".join(f"{k} {', '.join(v)}" for k, v in r["mixed"].items())
        for r in rows
        if r["mixed"]
    ]
    if mixed:
        lines += [
            "",
            "Cells whose finished runs chose a field differently (`report table` and `claims` keep such "
            "runs apart: give new runs the same --set):",
            *mixed,
        ]
    if grid["outside"]:
        lines += ["", "Runs in no cell of this grid:", *grid["outside"]]
    if grid["elsewhere"]:
        lines += ["", f"{len(grid['elsewhere'])} run(s) of other tasks or methods (not asked for)"]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="python -m dear_jax.report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("params", help="parameter counts per method and module")
    p.add_argument("--action-dim", type=int, default=6, help="|A| (walker: 6)")
    t = sub.add_parser("table", help="Table II for finished runs")
    t.add_argument("runs", nargs="+", help="run workdirs")
    t.add_argument(
        "--threshold",
        type=float,
        default=None,
        help="return for sample efficiency (default: 500; the kitchen's 1, every episode a success)",
    )
    t.add_argument("--out", default=None, help="also write OUT.md and OUT.csv")
    t.add_argument(
        "--at", type=int, default=None, help="read the evaluations up to this many frames per seed"
    )
    t.add_argument("--last", type=int, default=11, help="evaluations a seed's mean return averages")
    c = sub.add_parser("curves", help="learning curves: a panel per task, a line per method")
    c.add_argument("runs", nargs="+", help="run workdirs")
    c.add_argument("--out", default="curves.png", help="PNG path")
    c.add_argument("--metric", default="episode_return", help="eval.csv column (e.g. success)")
    c.add_argument("--band", default="std", choices=plot.BANDS, help="shaded spread over seeds")
    k = sub.add_parser("claims", help="the paper's claims, checked on finished runs")
    k.add_argument("runs", nargs="+", help="run workdirs")
    k.add_argument(
        "--threshold", type=float, default=None, help="return for sample efficiency (as table's)"
    )
    k.add_argument("--at", type=int, default=None, help="read evaluations up to this frame")
    k.add_argument("--last", type=int, default=11, help="evaluations a seed's return averages")
    k.add_argument("--out", default=None, help="also write OUT.md and OUT.json")
    o = sub.add_parser("cosines", help="the cosine between the latent halves, eval and train")
    o.add_argument("runs", nargs="+", help="run workdirs")
    o.add_argument("--rows", type=int, default=20, help="training-log rows to average")
    o.add_argument("--at", type=int, default=None, help="read the logs up to this frame")
    o.add_argument("--out", default=None, help="also write OUT.md")
    e = sub.add_parser("evals", help="whether a run's evaluations kept up with its training")
    e.add_argument("runs", nargs="+", help="run workdirs")
    e.add_argument("--out", default=None, help="also write OUT.md")
    g = sub.add_parser("grid", help="how far the runs have taken the paper's grid")
    g.add_argument("runs", nargs="+", help="run workdirs")
    g.add_argument("--tasks", nargs="+", default=["walker", "cup", "finger"], help=TASKS_HELP)
    g.add_argument("--methods", nargs="+", default=["dear", "sear", "ted", "drqv2"])
    g.add_argument("--seeds", type=positive_int, default=3, help="seeds per cell")
    g.add_argument("--frames", type=positive_int, default=1_000_000, help="frames per seed")
    g.add_argument("--seeds-per-run", type=int, default=1, help=SEEDS_PER_RUN_HELP)
    args = parser.parse_args(argv)
    if args.command == "grid":
        try:
            print(
                grid_table(
                    args.runs, args.tasks, args.methods, args.seeds, args.frames, args.seeds_per_run
                )
            )
        except (FileNotFoundError, ValueError, KeyError) as e:
            parser.error(str(e))
    if args.command == "evals":
        try:
            print(evals_table(args.runs, args.out)[1])
        except (FileNotFoundError, ValueError) as e:
            parser.error(str(e))
    if args.command == "cosines":
        try:
            text = cosines_table(args.runs, args.rows, args.at)[1]
        except (FileNotFoundError, ValueError) as e:
            parser.error(str(e))
        print(text)
        if args.out:
            pathlib.Path(args.out).with_suffix(".md").write_text(text)
    if args.command == "claims":
        try:
            print(claims.claims_table(args.runs, args.threshold, args.at, args.last, args.out)[1])
        except (FileNotFoundError, ValueError) as e:
            parser.error(str(e))
    if args.command == "curves":
        try:
            path = plot.plot(args.runs, args.out, metric=args.metric, band=args.band)
        except (FileNotFoundError, KeyError, ValueError) as e:
            parser.error(e.args[0] if e.args else str(e))
        print(path)
        return path
    if args.command == "table":
        try:
            print(runs_table(args.runs, args.threshold, args.out, args.at, args.last)[1])
        except (FileNotFoundError, ValueError) as e:
            parser.error(str(e))
    if args.command == "params":
        print(f"Parameters per module, |A| = {args.action_dim}")
        print(format_params_table(params_table(args.action_dim)))


if __name__ == "__main__":
    main()
