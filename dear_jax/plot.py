"""Learning curves from run workdirs: `python -m dear_jax.plot WORKDIR [WORKDIR ...]`.

Reads WORKDIR/config.json (agent.method, env.task, the sweep) and its lanes' eval.csv, and draws
the mean over seeds of one eval metric against frames, with a shaded band (min..max over seeds, or
mean ± std), one line per experiment (per setting of a sweep: `dear_jax/lanes.py`) and one
subplot per task. Workdirs that ran seeds of the same experiment (the same config but for its
seeds: other machines, other days) make one line with all their seeds. `python -m
dear_jax.report curves` draws the same figure.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import warnings
from collections.abc import Sequence

import numpy as np

from dear_jax import lanes
from dear_jax.logger import read_csv
from envs import distractions

# An evaluation starts at the first step at or after its mark (10,016 frames for 10,000): frames
# this close count as the same point of training (evaluations are 10k frames apart by default).
SLACK = 1_000


def slack(config: dict) -> float:
    """SLACK for a run of `config`, at most half its evaluations' spacing."""
    return min(SLACK, config.get("eval_every_frames", 10_000) / 2)


BANDS = ("minmax", "std")
_BAND_TEXT = {"minmax": "shaded: min..max over seeds", "std": "shaded: mean ± std over seeds"}


class Curve:
    """One workdir's (one setting's) metric per seed on a shared x grid."""

    def __init__(
        self,
        workdir: pathlib.Path,
        task: str,
        method: str,
        x: np.ndarray,
        y: np.ndarray,
        setting: str = "",
    ):
        self.workdir, self.task, self.method, self.setting = workdir, task, method, setting
        self.x = x  # [N] sorted union of the seeds' x values
        self.y = y  # [S, N], NaN where a seed has no row at that x
        self.label = f"{method} {setting}".strip()
        self.workdirs = [workdir]  # the runs its seeds come from


def task_name(config: dict) -> str:
    """A run's task as figures and tables name it: the DMC task with its distraction, if any
    ("walker-walk, distracting medium background", "..., distracting medium full suite")."""
    env = config.get("env", {})
    task, difficulty = env.get("task", "?"), env.get("distraction", "none")
    if difficulty == "none":
        return task
    types = distractions.parse_types(env.get("distraction_types", "all"))  # "all" before the field
    kinds = "full suite" if types == distractions.DISTRACTION_TYPES else "+".join(types)
    return f"{task}, distracting {difficulty} {kinds}" + (" dynamic" if env.get("dynamic") else "")


def pools(workdirs: Sequence[str | os.PathLike]) -> list[lanes.Pool]:
    """The workdirs' seeds pooled by experiment and setting (`lanes.pools`): runs of the same
    config (but for its seeds and the fields a run may change without changing what it learns)
    are one experiment, wherever and whenever they ran."""
    from dear_jax.experiment import RESUMABLE_CHANGES

    try:
        from configs.base import get_config
    except ImportError:  # the package without the repository's configs/: no defaults to fill
        defaults = {}
    else:
        defaults = lanes.flatten(get_config().to_dict())
    return lanes.pools(workdirs, defaults, ignored=(*RESUMABLE_CHANGES, "seeds"))


def pool_curve(pool: lanes.Pool, metric: str, x: str = "frame") -> Curve:
    """One pooled setting's metric per seed."""
    paths = [d / "eval.csv" for _, d in pool.seeds]
    absent = [p for p in paths if not p.is_file()]
    if absent:  # a seed left out would change the curve's n without a word
        raise FileNotFoundError(
            f"no eval log {absent[0]} of {pool.workdirs[0]}"
            + (f" (and {len(absent) - 1} more)" if len(absent) > 1 else "")
            + " (written after the first evaluation)"
        )
    x_grid, y, ends = _series(paths, metric, x, slack(pool.config))
    if not x_grid.size:
        empty = [str(p) for p, end in zip(paths, ends) if not np.isfinite(end)]
        raise ValueError(
            f"no evaluation that every seed of {pool.workdirs[0]} has"
            + (f": no rows in {', '.join(empty)}" if empty else "")
        )
    method = pool.config.get("agent", {}).get("method", "?")
    curve = Curve(pool.workdirs[0], task_name(pool.config), method, x_grid, y, pool.label)
    curve.workdirs = pool.workdirs
    # Where the line stops before its longest seed's last evaluation (a seed stopped early, or
    # still training), the legend says so.
    curve.cut = x == "frame" and x_grid[-1] < np.nanmax(ends) - slack(pool.config)
    return curve


def load_curves(workdir: str | os.PathLike, metric: str, x: str = "frame") -> list[Curve]:
    """The curves of one workdir: one, or one per setting of its sweep."""
    return [pool_curve(p, metric, x) for p in pools([workdir])]


def _series(
    paths: list[pathlib.Path], metric: str, x: str, near: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(the x grid, each seed's metric on it [S, N], each seed's last x: NaN for no rows)."""
    series = []
    for path in paths:
        cols = read_csv(path)
        for name in (x, metric):
            if name not in cols:
                raise KeyError(f"{path} has no column {name!r}; columns: {', '.join(cols)}")
        series.append((cols[x], cols[metric]))
    grid = np.unique(np.concatenate([xs[np.isfinite(xs)] for xs, _ in series]))
    if x == "frame":  # evaluations `near` frames apart or closer (10,000, 10,016) are one point
        starts = np.diff(grid, prepend=-np.inf) > near
        grid = grid[starts]
    ends = np.array([np.nanmax(xs) if np.isfinite(xs).any() else np.nan for xs, _ in series])
    y = np.full((len(series), len(grid)), np.nan)
    for s, (xs, ys) in enumerate(series):
        ok = np.isfinite(xs)
        y[s, np.searchsorted(grid, xs[ok], side="right") - 1] = ys[ok]
    if x == "frame":  # only the points every seed has: a mean over fewer seeds would jump
        shared = np.isfinite(y).all(0)
        grid, y = grid[shared], y[:, shared]
    return grid, y, ends


def _set_labels(curves: list[Curve]) -> None:
    several_tasks = len({c.task for c in curves}) > 1
    for c in curves:
        name = f"{c.method} {c.setting}".strip()
        c.label = f"{c.task} {name}" if several_tasks else name
    counts = {}
    for c in curves:
        counts[c.label] = counts.get(c.label, 0) + 1
    for c in curves:
        if counts[c.label] > 1:
            c.label = f"{c.label} ({c.workdir.resolve().name})"


def plot(
    workdirs: Sequence[str | os.PathLike],
    out: str | os.PathLike | None = None,
    *,
    metric: str = "episode_return",
    x: str = "frame",
    band: str = "minmax",
) -> pathlib.Path:
    """Draw the curves of `workdirs` (seeds of one experiment pooled) into a PNG; returns its
    path."""
    if not workdirs:
        raise ValueError("give at least one workdir")
    if band not in BANDS:
        raise ValueError(f"unknown band {band!r}; valid: {', '.join(BANDS)}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [pool_curve(p, metric, x) for p in pools(workdirs)]
    _set_labels(curves)
    if out is None:
        out = pathlib.Path(workdirs[0]) / "curves.png" if len(workdirs) == 1 else "curves.png"
    out = pathlib.Path(out)
    if not out.suffix:  # what matplotlib writes for a name without one: the path returned
        out = out.with_suffix(".png")
    tasks = list(dict.fromkeys(c.task for c in curves))
    # One colour per method (or per workdir label without its task), the same in every subplot.
    keys = list(dict.fromkeys(c.label.removeprefix(f"{c.task} ") for c in curves))
    colour = {k: f"C{i % 10}" for i, k in enumerate(keys)}
    fig, axes = plt.subplots(
        1, len(tasks), figsize=(5.5 * len(tasks), 5), squeeze=False, constrained_layout=True
    )
    for ax, task in zip(axes[0], tasks):
        for c in (c for c in curves if c.task == task):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a seed without a row at some x
                mean = np.nanmean(c.y, 0)
                if band == "minmax":
                    lo, hi = np.nanmin(c.y, 0), np.nanmax(c.y, 0)
                else:
                    std = np.nanstd(c.y, 0)
                    lo, hi = mean - std, mean + std
            name = c.label.removeprefix(f"{c.task} ")  # the panel's title names the task
            col = colour[name]
            marker = "o" if len(c.x) <= 40 else None
            runs = f", {len(c.workdirs)} runs" if len(c.workdirs) > 1 else ""
            cut = f"; to {c.x[-1] / 1000:,.0f}k, a seed's last" if getattr(c, "cut", False) else ""
            label = f"{name} (n={c.y.shape[0]}{runs}{cut})"
            ax.plot(c.x, mean, color=col, marker=marker, ms=3, label=label)
            ax.fill_between(c.x, lo, hi, color=col, alpha=0.2, linewidth=0)
        ax.set_title(task)
        ax.set_xlabel(f"{x}s per seed" if x == "frame" else x)
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        # Below the axes, where it hides no curve (constrained_layout makes room for it).
        ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.15))
    fig.suptitle(f"{metric}: mean over seeds; {_BAND_TEXT[band]}", fontsize="medium")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> pathlib.Path:
    parser = argparse.ArgumentParser(prog="python -m dear_jax.plot", description=__doc__)
    parser.add_argument("workdirs", nargs="+", help="run workdirs (with config.json, seed_*/)")
    parser.add_argument(
        "--out", default=None, help="PNG path (default: WORKDIR/curves.png, ./curves.png if many)"
    )
    parser.add_argument("--metric", default="episode_return", help="eval.csv column to plot")
    parser.add_argument("--x", default="frame", help="eval.csv column for the x axis")
    parser.add_argument("--band", default="minmax", choices=BANDS, help="shaded band")
    args = parser.parse_args(argv)
    try:
        path = plot(args.workdirs, args.out, metric=args.metric, x=args.x, band=args.band)
    except (FileNotFoundError, KeyError, ValueError) as e:
        parser.error(e.args[0] if e.args else str(e))
    print(path)
    return path


if __name__ == "__main__":
    main()
