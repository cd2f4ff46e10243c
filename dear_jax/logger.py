"""Per-seed run logs: one CSV per seed and kind, plus TensorBoard scalars, and small table helpers.

Layout under a run's workdir:
  seed_<i>/train.csv, seed_<i>/eval.csv   one row per `write`: frame first, then the metrics
  seed_<i>/tb/                            tensorboardX events, tags "<kind>/<metric>", step = frame
(a sweep's lanes use their names, `dear_jax/lanes.py`, in place of seed_<i>).

Every write is flushed, so a killed run keeps its logs. A resumed run (`resume_frame`) keeps the
rows up to the checkpoint's frame and drops the later ones, which the resumed run will log again
(and, for the kinds in `redo`, those at the checkpoint's frame too: an evaluation the checkpoint
holds as due);
TensorBoard is told the same by a purge marker (SessionLog START at resume_frame + 1; with a kind
to redo, at resume_frame, and the rows kept at that frame are written to it again). A fresh run
(`resume_frame=None`) starts new files in place of any left by an earlier run in that workdir.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import pathlib
import time
from collections.abc import Mapping, Sequence

import numpy as np

log = logging.getLogger(__name__)

KINDS = ("train", "eval")
FRAME = "frame"


def _replace_csv(path: pathlib.Path, columns: list[str], rows: list[dict]) -> None:
    """Write `rows` under `columns` in place of `path`, atomically."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, text.getvalue())


def write_text_atomic(path: pathlib.Path, text: str) -> None:
    """Write `text` to a temporary file, flushed to disk, then atomically put it in place of
    `path`: a reader sees the old file or the new one, never a part."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        f.write(text)
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


def _numbers(kind: str, row: dict) -> dict[str, float]:
    """A CSV row's metrics as TensorBoard scalars ("<kind>/<metric>"), the empty cells left out."""
    return {f"{kind}/{k}": float(v) for k, v in row.items() if k != FRAME and v not in ("", None)}


def _frame_of(row: dict) -> float:
    try:
        return float(row.get(FRAME, "nan"))
    except ValueError:
        return math.nan


class _EventWriter:
    """TensorBoard event file written synchronously.

    tensorboardX's SummaryWriter hands events to a background thread whose queue `flush()` does
    not drain, so a run killed right after a log call could lose it; here each call is on disk
    when it returns. Records are tensorboardX's protobufs in its TFRecord writer.
    """

    def __init__(self, logdir: pathlib.Path, *, purge_step: int | None = None):
        from tensorboardX.event_file_writer import EventsWriter
        from tensorboardX.proto import event_pb2, summary_pb2

        self._pb, self._summary_pb = event_pb2, summary_pb2
        logdir.mkdir(parents=True, exist_ok=True)
        # The name has whole seconds only; the suffix keeps a writer started in the same second
        # (a quick resume) from truncating the previous file.
        self._writer = EventsWriter(str(logdir / "events"), f".{time.time_ns()}")
        if purge_step is not None:
            # TensorBoard hides the earlier events at steps >= purge_step: a resumed run's.
            start = event_pb2.SessionLog(status=event_pb2.SessionLog.START)
            self._write(event_pb2.Event(step=purge_step, session_log=start))

    def _write(self, event) -> None:
        event.wall_time = time.time()
        self._writer.write_event(event)
        self._writer.flush()

    def scalars(self, step: int, values: Mapping[str, float]) -> None:
        summary = self._summary_pb.Summary(
            value=[self._summary_pb.Summary.Value(tag=t, simple_value=x) for t, x in values.items()]
        )
        self._write(self._pb.Event(step=step, summary=summary))

    def close(self) -> None:
        self._writer.close()


class RunLogger:
    """CSV + TensorBoard logs of `num_seeds` seeds (or lanes) trained together; `names` are
    their folders (default seed_<i>)."""

    def __init__(
        self,
        workdir: str | os.PathLike,
        num_seeds: int,
        *,
        tensorboard: bool = True,
        resume_frame: int | None = None,
        names: Sequence[str] | None = None,
        redo: Sequence[str] = (),
    ):
        if num_seeds < 1:
            raise ValueError(f"num_seeds must be >= 1, got {num_seeds}")
        self.names = list(names) if names is not None else [f"seed_{s}" for s in range(num_seeds)]
        if len(self.names) != num_seeds:
            raise ValueError(f"{len(self.names)} names for {num_seeds} seeds")
        self.workdir = pathlib.Path(workdir)
        self.num_seeds = num_seeds
        self._columns: dict[tuple[str, int], list[str]] = {}
        self._writers = []
        again: list[list[tuple[str, dict]]] = [[] for _ in range(num_seeds)]  # rows at the purge
        for seed in range(num_seeds):
            seed_dir = self.seed_dir(seed)
            seed_dir.mkdir(parents=True, exist_ok=True)
            for kind in KINDS:
                path = self.csv_path(kind, seed)
                if not path.exists():
                    continue
                if resume_frame is None:
                    _, rows = _read_rows(path)
                    if rows and kind == "train" and seed == 0:  # said once
                        log.warning(
                            "%s has no checkpoint to resume from: training starts at frame 0, "
                            "and its logs (%s, to frame %s) are replaced",
                            self.workdir,
                            path,
                            rows[-1].get(FRAME, "?"),
                        )
                    path.unlink()
                    continue
                columns, rows = _read_rows(path)
                # NaN frames (damaged rows) are dropped too: `nan <= x` is False.
                last = resume_frame - 1 if kind in redo else resume_frame
                kept = [r for r in rows if _frame_of(r) <= last]
                if len(kept) != len(rows):
                    _replace_csv(path, columns, kept)
                again[seed] += [(kind, r) for r in kept if _frame_of(r) == resume_frame]
                if columns:
                    self._columns[(kind, seed)] = columns
        if tensorboard:
            for seed in range(num_seeds):
                tb_dir = self.seed_dir(seed) / "tb"
                if resume_frame is None and tb_dir.is_dir():
                    for old in tb_dir.glob("events.out.tfevents.*"):
                        old.unlink()
                # TensorBoard drops the earlier events at steps >= purge: those logged again
                purge = None if resume_frame is None else int(resume_frame) + (not redo)
                writer = _EventWriter(tb_dir, purge_step=purge)
                for kind, row in again[seed] if redo else ():
                    writer.scalars(int(resume_frame), _numbers(kind, row))
                self._writers.append(writer)

    def seed_dir(self, seed: int) -> pathlib.Path:
        return self.workdir / self.names[seed]

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
                writer.scalars(
                    frame, {f"{kind}/{name}": float(v[seed]) for name, v in values.items()}
                )

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
