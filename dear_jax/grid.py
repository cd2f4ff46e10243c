"""Runs the paper's grid: every seed-run that `report grid` finds missing, as a queue over GPUs.

    python -m dear_jax.grid [RUN ...] [--root runs] [--gpus 0,1,2,3] [--per-gpu 1]
        [--tasks walker cup finger] [--methods dear sear ted drqv2] [--seeds 3]
        [--frames 1000000] [--set FIELD=VALUE ...] [--time-limit 3h] [--dry-run]

The runs named (workdirs of earlier runs, e.g. `results/*/*/`) and every run under --root count
towards the grid (`report.grid_rows`: a run belongs to a cell of `configs/paper.py:TASK,METHOD`
when its config is the cell's but for its seeds, envs per seed, dtype and replay). The queue
(`report.grid_jobs`): first each stopped run that kept a checkpoint, resumed in its workdir, then
one seed-run per missing seed in ROOT/TASK_METHOD_sSEED, task by task, the methods of a task
taking turns.

Each GPU runs --per-gpu jobs at a time (CUDA_VISIBLE_DEVICES), each job pinned to its equal share
of this process's cores; when a job ends the next starts. A job's console goes to
ROOT/NAME.out. At --time-limit (90m, 3h, 2h30m or seconds), or on SIGTERM or Ctrl-C, every running
job gets SIGTERM, saves a checkpoint and its summary, and exits; the same command later resumes
them. Without GPUs (none visible) the jobs run on the CPU, --per-gpu at a time. At the end: a
line per job (finished, failed, stopped, not started) and the grid as `report grid` prints it.

--set FIELD=VALUE (repeatable) sets a field of each new seed-run, e.g. `--set envs_per_seed=16
--set agent.compute_dtype=bfloat16 --set progress=False`: only the fields a grid run may choose
(`report.GRID_MAY_DIFFER` but its seeds, and `experiment.RESUMABLE_CHANGES` but its length).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import re
import shlex
import signal
import subprocess
import sys
import time

from dear_jax import report
from dear_jax.experiment import RESUMABLE_CHANGES
from dear_jax.logger import format_table

ROOT = pathlib.Path(__file__).resolve().parents[1]  # run.py and configs/ are here


@dataclasses.dataclass(frozen=True)
class Slot:
    """Where a job runs: a GPU (None: the CPU) and the cores it is pinned to."""

    gpu: str | None
    cores: tuple[int, ...]

    def __str__(self) -> str:
        where = "CPU" if self.gpu is None else f"GPU {self.gpu}"
        return f"{where}, cores {self.cores[0]}-{self.cores[-1]}"


def visible_gpus() -> list[str]:
    """The GPUs jobs may use: CUDA_VISIBLE_DEVICES if set, else every GPU nvidia-smi lists
    (none without a driver)."""
    if "CUDA_VISIBLE_DEVICES" in os.environ:
        return [g.strip() for g in os.environ["CUDA_VISIBLE_DEVICES"].split(",") if g.strip()]
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return []
    return out.split()


def slots(gpus: list[str], per_gpu: int) -> list[Slot]:
    """per_gpu slots on each GPU (on the CPU without GPUs), this process's cores split equally
    among them in order (each slot at least one core)."""
    if per_gpu < 1:
        raise ValueError(f"--per-gpu must be at least 1, got {per_gpu}")
    places = [g for g in gpus for _ in range(per_gpu)] if gpus else [None] * per_gpu
    cores = sorted(os.sched_getaffinity(0))
    share = max(1, len(cores) // len(places))
    return [
        Slot(gpu, tuple(cores[i * share : (i + 1) * share] or cores[-share:]))
        for i, gpu in enumerate(places)
    ]


def parse_duration(text: str) -> float:
    """Seconds of "5400", "90m", "3h", "2h30m" or "45s"."""
    if re.fullmatch(r"\d+(\.\d+)?", text):
        return float(text)
    parts = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:(\d+)s)?", text)
    if not text or parts is None:
        raise ValueError(f"time limit {text!r}: give seconds, or e.g. 90m, 3h, 2h30m")
    h, m, s = (int(p or 0) for p in parts.groups())
    return 3600.0 * h + 60.0 * m + s


def overrides(settings: list[str]) -> list[str]:
    """--set FIELD=VALUE items -> run.py's `--config.FIELD=VALUE`, each FIELD one a grid run may
    choose; otherwise a ValueError naming the valid ones."""
    may = [p for p in report.GRID_MAY_DIFFER if p not in ("seed", "seeds")]
    may += [f for f in RESUMABLE_CHANGES if f != "total_frames"]
    out = []
    for item in settings:
        field, eq, value = item.partition("=")
        ok = any(field == p or (p.endswith(".") and field.startswith(p)) for p in may)
        if not eq or not field or not ok:
            raise ValueError(
                f"--set {item!r}: give FIELD=VALUE with FIELD one a grid run may choose: "
                f"{', '.join(p + '*' if p.endswith('.') else p for p in may)} (the seeds come "
                "from the grid, the length from --frames; other fields make another experiment)"
            )
        out.append(f"--config.{field}={value}")
    return out


def _stamp(start: float) -> str:
    s = int(time.monotonic() - start)
    return f"[{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}]"


class Queue:
    """Runs `jobs` (`report.Job`), one per free slot, each as `command(job)` (an argv) in
    `cwd`, its console in log_dir/NAME.out, until all ended, the time limit passed or a signal
    came (then the running ones get SIGTERM and are waited for)."""

    def __init__(self, jobs, places, command, log_dir, cwd=ROOT, time_limit=None, poll=1.0):
        self.jobs, self.places, self.command = list(jobs), list(places), command
        self.log_dir, self.cwd, self.time_limit, self.poll = log_dir, cwd, time_limit, poll
        self.stopping = ""  # why the queue stops early: "" while it goes on

    def _stop(self, signum, _frame) -> None:
        self.stopping = signal.Signals(signum).name

    def _start(self, job, slot: Slot) -> subprocess.Popen:
        env = dict(os.environ)
        env["CUDA_VISIBLE_DEVICES"] = "" if slot.gpu is None else slot.gpu
        self.log_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_dir / f"{job.name}.out", "ab") as console:
            return subprocess.Popen(
                self.command(job),
                cwd=self.cwd,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=console,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # a terminal's Ctrl-C reaches the queue only
                preexec_fn=lambda: os.sched_setaffinity(0, slot.cores),
            )

    def run(self, echo=print) -> list[dict]:
        """A row per job: name, where, state (finished, failed, stopped, not started), return
        code and seconds."""
        start = time.monotonic()
        queued, free = list(self.jobs), list(self.places)
        running = {}  # Popen -> (job, slot, start)
        rows = {job.name: {"job": job.name, "where": "-", "state": "not started"} for job in queued}
        previous = {sig: signal.signal(sig, self._stop) for sig in (signal.SIGTERM, signal.SIGINT)}
        signalled = False
        try:
            while running or (queued and not self.stopping):
                if self.time_limit is not None and time.monotonic() - start >= self.time_limit:
                    self.stopping = self.stopping or "the time limit"
                while queued and free and not self.stopping:
                    job, slot = queued.pop(0), free.pop(0)
                    running[self._start(job, slot)] = (job, slot, time.monotonic())
                    rows[job.name].update(where=str(slot), state="running")
                    echo(f"{_stamp(start)} {job.name} started on {slot}; {len(queued)} queued")
                if self.stopping and not signalled:
                    echo(f"{_stamp(start)} stopping on {self.stopping}: SIGTERM to the runs")
                    for process in running:
                        process.send_signal(signal.SIGTERM)
                    signalled = True
                time.sleep(self.poll)
                for process in [p for p in running if p.poll() is not None]:
                    job, slot, began = running.pop(process)
                    rc, seconds = process.returncode, round(time.monotonic() - began)
                    state = "finished" if rc == 0 else "stopped" if signalled else "failed"
                    rows[job.name].update(state=state, rc=rc, seconds=seconds)
                    echo(f"{_stamp(start)} {job.name} {state} (rc {rc}, {seconds:,} s)")
                    free.append(slot)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return list(rows.values())


def main(argv=None) -> list[dict] | None:
    parser = argparse.ArgumentParser(
        prog="python -m dear_jax.grid",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="*", help="workdirs of earlier runs that count")
    parser.add_argument("--root", default="runs", help="folder of the new runs")
    parser.add_argument("--gpus", default=None, help="e.g. 0,1,2,3 (default: every visible GPU)")
    parser.add_argument("--per-gpu", type=int, default=1, help="jobs at a time on each GPU")
    parser.add_argument("--tasks", nargs="+", default=["walker", "cup", "finger"])
    parser.add_argument("--methods", nargs="+", default=["dear", "sear", "ted", "drqv2"])
    parser.add_argument("--seeds", type=int, default=3, help="seeds per cell")
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames per seed")
    parser.add_argument("--set", action="append", default=[], help="FIELD=VALUE for new runs")
    parser.add_argument("--time-limit", default=None, help="e.g. 90m, 3h: then SIGTERM the runs")
    parser.add_argument("--dry-run", action="store_true", help="print the queue, run nothing")
    args = parser.parse_args(argv)
    if str(ROOT) not in sys.path:  # configs/, as run.py finds it
        sys.path.insert(0, str(ROOT))
    root = pathlib.Path(args.root).resolve()
    try:
        limit = None if args.time_limit is None else parse_duration(args.time_limit)
        extra = overrides(args.set)
        gpus = visible_gpus() if args.gpus is None else [g for g in args.gpus.split(",") if g]
        places = slots(gpus, args.per_gpu)
        workdirs = [*args.runs, *(p.parent for p in sorted(root.glob("*/config.json")))]
        grid = report.grid_rows(workdirs, args.tasks, args.methods, args.seeds, args.frames)
    except (FileNotFoundError, ValueError, KeyError) as e:
        parser.error(str(e))
    jobs = report.grid_jobs(grid, args.frames, str(root), extra)
    print(f"{len(jobs)} runs to complete the grid, {len(places)} at a time:")
    print("\n".join(f"  {job.name}: python run.py {shlex.join(job.args)}" for job in jobs))
    if args.dry_run or not jobs:
        return None
    queue = Queue(
        jobs,
        places,
        lambda job: [sys.executable, str(ROOT / "run.py"), *job.args],
        root,
        time_limit=limit,
    )
    rows = queue.run()
    columns = ["job", "where", "state", "rc", "seconds"]
    print(format_table(columns, [[r.get(c, "-") for c in columns] for r in rows]))
    done = [*args.runs, *(p.parent for p in sorted(root.glob("*/config.json")))]
    print(report.grid_table(done, args.tasks, args.methods, args.seeds, args.frames))
    if queue.stopping in ("SIGTERM", "SIGINT"):
        sys.exit(128 + signal.Signals[queue.stopping])
    return rows


if __name__ == "__main__":
    main()
