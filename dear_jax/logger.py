"""Per-seed run logs: one CSV per seed and kind, plus TensorBoard scalars, and small table helpers.

Layout under a run's workdir:
  seed_<i>/train.csv, seed_<i>/eval.csv   one row per `write`: frame first, then the metrics
  seed_<i>/tb/                            tensorboardX events, tags "<kind>/<metric>", step = frame

Every write is flushed, so a killed run keeps its logs. A resumed run (`resume_frame`) keeps the
rows up to the checkpoint's frame and drops the later ones, which the resumed run will log again;
TensorBoard is told the same through `purge_step`. A fresh run (`resume_frame=None`) starts new
files in place of any left by an earlier run in that workdir.
"""

from __future__ import annotations

import csv
import math
import os
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np

KINDS = ("train", "eval")
FRAME = "frame"


def _replace_csv(path: pathlib.Path, columns: list[str], rows: list[dict]) -> None:
    """Write `rows` under `columns` to a temporary file, then atomically put it in place."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_rows(path: pathlib.Path) -> tuple[list[str], list[dict]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def _cell(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(int(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return repr(float(value))  # shortest string that reads back to the same float


def _frame_of(row: dict) -> float:
    try:
        return float(row.get(FRAME, "nan"))
    except ValueError:
        return math.nan


class RunLogger:
    """CSV + TensorBoard logs of `num_seeds` seeds trained together."""

    def __init__(
        self,
        workdir: str | os.PathLike,
        num_seeds: int,
        *,
        tensorboard: bool = True,
        resume_frame: int | None = None,
    ):
        if num_seeds < 1:
            raise ValueError(f"num_seeds must be >= 1, got {num_seeds}")
        self.workdir = pathlib.Path(workdir)
        self.num_seeds = num_seeds
        self._columns: dict[tuple[str, int], list[str]] = {}
        self._writers = []
        for seed in range(num_seeds):
            seed_dir = self.seed_dir(seed)
            seed_dir.mkdir(parents=True, exist_ok=True)
            for kind in KINDS:
                path = self.csv_path(kind, seed)
                if not path.exists():
                    continue
                if resume_frame is None:
                    path.unlink()
                    continue
                columns, rows = _read_rows(path)
                # NaN frames (damaged rows) are dropped too: `nan <= x` is False.
                kept = [r for r in rows if _frame_of(r) <= resume_frame]
                if len(kept) != len(rows):
                    _replace_csv(path, columns, kept)
                if columns:
                    self._columns[(kind, seed)] = columns
        if tensorboard:
            from tensorboardX import SummaryWriter

            for seed in range(num_seeds):
                tb_dir = self.seed_dir(seed) / "tb"
                if resume_frame is None and tb_dir.is_dir():
                    for old in tb_dir.glob("events.out.tfevents.*"):
                        old.unlink()
                # purge_step: TensorBoard hides the old run's events from this frame on.
                purge = None if resume_frame is None else int(resume_frame) + 1
                self._writers.append(
                    SummaryWriter(logdir=str(tb_dir), purge_step=purge, flush_secs=10)
                )

    def seed_dir(self, seed: int) -> pathlib.Path:
        return self.workdir / f"seed_{seed}"

    def csv_path(self, kind: str, seed: int) -> pathlib.Path:
        return self.seed_dir(seed) / f"{kind}.csv"

    def _per_seed(self, name: str, value) -> np.ndarray:
        """`value` as a [num_seeds] array: scalars broadcast, [num_seeds] arrays kept."""
        arr = np.asarray(value)
        if arr.ndim == 0:
            return np.broadcast_to(arr, (self.num_seeds,))
        if arr.shape != (self.num_seeds,):
            raise ValueError(
                f"metric {name!r} has shape {arr.shape}; expected a scalar or "
                f"({self.num_seeds},) (one value per seed)"
            )
        return arr

    def write(self, kind: str, frame: int, metrics: Mapping[str, np.ndarray | float]) -> None:
        """Append one row per seed to seed_<i>/<kind>.csv and the TensorBoard scalars."""
        if kind not in KINDS:
            raise ValueError(f"unknown log kind {kind!r}; valid: {', '.join(KINDS)}")
        if FRAME in metrics:
            raise ValueError(f"{FRAME!r} is the x column; pass it as the `frame` argument")
        frame = int(frame)
        values = {name: self._per_seed(name, v) for name, v in metrics.items()}
        for seed in range(self.num_seeds):
            row = {FRAME: str(frame)}
            row.update({name: _cell(v[seed]) for name, v in values.items()})
            self._append(kind, seed, row)
            if self._writers:
                writer = self._writers[seed]
                for name, v in values.items():
                    writer.add_scalar(f"{kind}/{name}", float(v[seed]), global_step=frame)
                writer.flush()

    def _append(self, kind: str, seed: int, row: dict) -> None:
        path = self.csv_path(kind, seed)
        columns = self._columns.get((kind, seed))
        if columns is None:
            columns = list(row)
            _replace_csv(path, columns, [row])
        elif set(row) - set(columns):
            columns = columns + [c for c in row if c not in columns]
            _, rows = _read_rows(path)
            _replace_csv(path, columns, [*rows, row])
        else:
            with open(path, "a", newline="") as f:
                csv.DictWriter(f, fieldnames=columns, restval="").writerow(row)
                f.flush()
        self._columns[(kind, seed)] = columns

    def close(self) -> None:
        for writer in self._writers:
            writer.close()
        self._writers = []

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of a log CSV as float64 arrays; empty or unparsable cells are NaN."""
    columns, rows = _read_rows(pathlib.Path(path))

    def number(cell) -> float:
        try:
            return float(cell)
        except (TypeError, ValueError):
            return math.nan

    return {c: np.array([number(r.get(c)) for r in rows], dtype=np.float64) for c in columns}


def _is_number(cell: str) -> bool:
    try:
        float(cell.replace(",", "").split(" ")[0])
    except ValueError:
        return False
    return True


def format_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A markdown table with padded columns; columns whose cells are all numbers align right."""
    header = [str(h) for h in header]
    body = [[str(c) for c in row] for row in rows]
    for i, row in enumerate(body):
        if len(row) != len(header):
            raise ValueError(f"row {i} has {len(row)} cells; the header has {len(header)}")
    widths = [max([len(header[j]), 3, *(len(r[j]) for r in body)]) for j in range(len(header))]
    right = [bool(body) and all(_is_number(r[j]) for r in body if r[j]) for j in range(len(header))]

    def line(cells):
        padded = [c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right)]
        return "| " + " | ".join(padded) + " |"

    rule = "|" + "|".join("-" * (w + 1) + (":" if r else "-") for w, r in zip(widths, right)) + "|"
    return "\n".join([line(header), rule, *(line(r) for r in body)])
