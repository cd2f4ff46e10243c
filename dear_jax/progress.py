"""What a run reports while it trains: the progress bar (on a terminal only) and the train log's
rows (`TrainLog`: one per log interval, once an update or an episode has ended since the last)."""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable

import numpy as np

from dear_jax.devices import Hosts
from dear_jax.logger import RunLogger

log = logging.getLogger("dear_jax")


class Progress:
    """The progress bar of frames per seed, with the latest rate and evaluation return; none
    off a terminal or with `show` off (detached runs log a line per log interval instead)."""

    def __init__(self, show: bool, total: int, initial: int):
        self.bar = None
        self.total = total
        self.last_eval_return = None
        if show and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                initial=initial,
                unit="frame",
                desc="frames per seed",
                smoothing=0.05,
                dynamic_ncols=True,
            )

    def advance(self, frames: int) -> None:
        if self.bar is not None:
            self.bar.update(frames)

    def show_rate(self, fps: float, refresh: bool = True) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(self._postfix(fps), refresh=refresh)

    def _postfix(self, fps) -> str:
        parts = [f"{fps:.0f} frames/s in all"] if np.isfinite(fps) else []
        if self.last_eval_return is not None:
            parts.append(f"eval return {self.last_eval_return:.1f}")
        return ", ".join(parts)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _left(frame: int, total: int, fps_per_seed: float) -> str:
    """How far a run is and, at `fps_per_seed`, how long its training has left: "25% of
    1,000,000, ~12 min left" (evaluations that hold the loop up not counted)."""
    done = f"{min(frame / max(total, 1), 1):.0%} of {total:,}"
    if not fps_per_seed > 0:  # NaN: no rate yet
        return done
    minutes = max(total - frame, 0) / fps_per_seed / 60
    return f"{done}, ~{minutes:.0f} min left" if minutes >= 1 else f"{done}, <1 min left"


class TrainLog:
    """The train log's rows: the training metrics averaged since the last row, the mean return of
    the episodes ended since then, the rate in frames per second over all lanes, and where an
    iteration's time went on the host (`host_seconds`: a callable returning the seconds spent
    since its last call by stage, logged as `<stage>_ms` per iteration, beside `iteration_ms` and
    the row's `iterations`). A row whose interval holds this process's compilations (its first
    row, and the row of its first update: `updates` is the count it starts from) leaves those
    timings empty: they would describe the compiler, not an iteration."""

    def __init__(
        self,
        logger: RunLogger,
        progress: Progress,
        hosts: Hosts,
        num_lanes: int,
        every_frames: int,
        t0: float,
        iteration: int,
        updates: int,
        host_seconds: Callable[[], dict[str, float]],
    ):
        self.logger, self.progress, self.hosts = logger, progress, hosts
        self.num_lanes, self.every_frames, self.last_t = num_lanes, every_frames, t0
        self.last_iteration, self.host_seconds = iteration, host_seconds
        self.first_updates = self.last_updates = updates
        self.rows = 0  # rows this process wrote

    def write_if_due(self, carry) -> None:
        """A row, if the log interval has passed and something happened since the last one
        (`carry`: the loop's `Carry`, whose sums the row takes and resets)."""
        counters, lv = carry.counters, carry.lv
        frame = counters["frame"]
        # Both reasons to log are the same on every process (a process whose lanes ended no
        # episode logs a row without a return).
        if frame < lv["next_log"] or not (lv["metric_count"] or carry.episodes_pending):
            return
        carry.episodes_pending = False
        now = time.perf_counter()
        iterations = max(counters["iteration"] - self.last_iteration, 1)
        timings = {
            "iteration_ms": (now - self.last_t) * 1e3 / iterations,
            **{f"{k}_ms": s * 1e3 / iterations for k, s in self.host_seconds().items()},
        }
        first_update = self.last_updates == self.first_updates < counters["updates"]
        if self.rows == 0 or first_update:
            timings = dict.fromkeys(timings, math.nan)
        row = {
            "episode": counters["episode"],
            "updates": counters["updates"],
            "fps": (frame - lv["last_log_frame"]) * self.num_lanes / max(now - self.last_t, 1e-9),
            "iterations": iterations,
            **timings,
        }
        if lv["metric_count"]:
            row.update(
                {k: self.hosts.read(v) / lv["metric_count"] for k, v in carry.metric_sum.items()}
            )
            carry.metric_sum, lv["metric_count"] = None, 0
        if carry.episode_returns:
            total, count = np.sum(carry.ended_episodes(), 0)
            with np.errstate(invalid="ignore", divide="ignore"):  # no episode ended: NaN
                row["episode_return"] = total / count
            carry.episode_returns = []
        self.logger.write("train", frame, row)
        self.progress.show_rate(row["fps"], refresh=False)
        # Detached runs (no bar) show this line on the console; with a bar only the file has it.
        log.info(
            "frame %d per seed: %.0f frames/s in all; %s",
            frame,
            row["fps"],
            _left(frame, self.progress.total, row["fps"] / self.num_lanes),
            extra={"console": self.progress.bar is None},
        )
        self.last_t, lv["last_log_frame"] = now, frame
        self.last_iteration, self.last_updates = counters["iteration"], counters["updates"]
        self.rows += 1
        lv["next_log"] = frame + self.every_frames
