"""Runs the paper's grid: every seed-run that `report grid` finds missing, as a queue over GPUs.

    python -m dear_jax.grid [RUN ...] [--root runs] [--gpus 0,1,2,3] [--per-gpu 1]
        [--tasks walker cup finger] [--methods dear sear ted drqv2] [--seeds 3]
        [--frames 1000000] [--seeds-per-run 1] [--set FIELD=VALUE ...]
        [--time-limit 3h [--start-margin 60|auto[:MARGIN]]] [--dry-run]

The runs named (workdirs of earlier runs, e.g. `results/*/*/`) and every run under --root count
towards the grid (`report.grid_rows`: a run belongs to a cell of `configs/paper.py:TASK,METHOD`
when its config is the cell's but for its seeds, envs per seed, dtype and replay; a task given
with more of paper.py's parts makes cells of that setting: `--tasks walker,medium-full` of the
full suite, `walker,beta=10` of a weight ablation's setting, for the methods that read beta). The
queue (`report.grid_jobs`): first the stopped runs that kept a checkpoint and their replay and
bring missing seeds, resumed in their workdirs, then one seed-run per missing seed that no run
brings (a running one's seeds count; --seeds-per-run K: per K missing seeds, trained as lanes of
one process), with the dtype, envs per seed and replay settings the cell's finished runs all
chose (--set overrides them), in --root as TASK_METHOD_sSEED (with the task's other parts:
walker_beta=10_dear_s0), task by task, the methods of a task taking turns.

Each GPU (`--gpus`: ids as CUDA_VISIBLE_DEVICES takes them, in nvidia-smi's PCI order; default
every GPU visible) runs --per-gpu jobs at a time, each pinned (taskset) to its equal share of
this process's cores, with its share of the GPU's memory when several share it, and told how
many do ($DEAR_JAX_RUNS_PER_GPU, which its summary records); when a job ends the next starts.
A job's console goes to --root as NAME.out. At --time-limit (90m, 3h, 2h30m or seconds; no
job starts in its last --start-margin, a minute by default: give a job's length where
a stopped job cannot resume; `auto`: a job starts only where a minute plus 1.1x its length fit,
its length at the training pace of its cell's finished runs of as many lanes (each alone on
its GPU), else of its task
and method's in other settings, else at most that of runs of other lane counts
(`report.grid_jobs`; their periodic checkpoints' share too unless
--set checkpoint_every_frames=0; with --per-gpu K > 1, at most K times that, as K jobs share a
GPU and its cores; a job without one needs MARGIN of `auto:MARGIN`, a minute by
default), and where the next job does not fit, a later one that does goes first; with a fixed
margin, the queue printed first warns of the jobs whose lengths pass the limit), or on SIGTERM,
SIGINT (Ctrl-C) or SIGHUP, every running job gets SIGTERM, saves a checkpoint and its summary,
and exits; a second signal stops them at once, and one still running 10 minutes after the first
gets SIGKILL. The same command later resumes them.
Without GPUs the jobs run on the CPU, --per-gpu at a time. At the end: a line
per job (finished, stopped, failed, killed, not started) and the grid as `report grid` prints it.
Exit status: 0 when every job finished, 1 when one failed, 75 when the time limit left some
unfinished, 128 + the signal's number after a signal.

--set FIELD=VALUE (repeatable) sets a field of each new seed-run, e.g. `--set envs_per_seed=16
--set agent.compute_dtype=bfloat16 --set progress=False`: only a field a grid run chooses for
itself (`report.grid_run_fields`, but its seeds).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import pathlib
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time

from dear_jax import lanes, report
from dear_jax.logger import format_table
from dear_jax.signals import SIGNALS
from dear_jax.summary import RUNS_PER_GPU_ENV

REPO = pathlib.Path(__file__).resolve().parents[1]  # run.py and configs/ are here
STOPPED = (143, 130, -signal.SIGTERM, -signal.SIGINT)  # how a run ends when asked to stop
START_MARGIN_S = 60.0  # no job starts this close to the time limit
FIT_FACTOR = 1.1  # --start-margin auto: a job's length by earlier runs, times this, must fit
KILL_AFTER_S = 600.0  # a run still going this long after its SIGTERM gets SIGKILL
EX_TEMPFAIL = 75  # the time limit left jobs unfinished: run the same command again


def _ranges(cores) -> str:
    """[0, 1, 2, 5] -> "0-2,5"."""
    out, start = [], None
    for i, c in enumerate(cores):
        if start is None:
            start = c
        if i + 1 == len(cores) or cores[i + 1] != c + 1:
            out.append(str(c) if c == start else f"{start}-{c}")
            start = None
    return ",".join(out)


@dataclasses.dataclass(frozen=True)
class Slot:
    """Where a job runs: a GPU (None: the CPU), the cores it is pinned to, and the share of the
    GPU's memory JAX may take (None: JAX's default)."""

    gpu: str | None
    cores: tuple[int, ...]
    memory_fraction: float | None = None
    per_gpu: int = 1  # jobs at a time on its GPU (or the CPU), its own included

    def __str__(self) -> str:
        where = "CPU" if self.gpu is None else f"GPU {self.gpu}"
        return f"{where}, cores {_ranges(self.cores)}"

    def env(self) -> dict[str, str]:
        """The job's environment: this process's, with its GPU (and memory share), and how many
        jobs run beside it there (its summary records it: `summary.RUNS_PER_GPU_ENV`)."""
        env = dict(os.environ, CUDA_VISIBLE_DEVICES="" if self.gpu is None else self.gpu)
        env[RUNS_PER_GPU_ENV] = str(self.per_gpu)
        env.setdefault("CUDA_DEVICE_ORDER", "PCI_BUS_ID")  # nvidia-smi's numbering
        if self.memory_fraction is not None:
            env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{self.memory_fraction:.2f}")
        return env


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
    """per_gpu slots on each GPU (on the CPU without GPUs), this process's cores split among
    them in order, as equally as they go (more slots than cores: one core each, in turn); slots
    sharing a GPU share its memory (0.9 of it in all)."""
    if per_gpu < 1:
        raise ValueError(f"--per-gpu must be at least 1, got {per_gpu}")
    places = [g for g in gpus for _ in range(per_gpu)] if gpus else [None] * per_gpu
    cores = sorted(os.sched_getaffinity(0))
    n, m = len(places), len(cores)
    fraction = 0.9 / per_gpu if gpus and per_gpu > 1 else None
    return [
        Slot(gpu, tuple(cores[i * m // n : (i + 1) * m // n] or [cores[i % m]]), fraction, per_gpu)
        for i, gpu in enumerate(places)
    ]


def shared_gpu_lengths(jobs: list[report.Job], at_a_time: int) -> list[report.Job]:
    """The jobs' lengths where `at_a_time` of them run at a time on each GPU (or on the
    CPU): at most that many times their length by the paces of earlier runs alone on theirs
    (`report.grid_jobs`), as the jobs share the GPU and split its cores (one after the other
    they would take no longer). Measured, two
    finger-spin runs side by side on one H200 with 8 cores each took 1.5x as long as alone
    (results/README.md), so `auto` would start jobs that the time limit then stops."""
    if at_a_time == 1:
        return list(jobs)
    return [
        job
        if job.seconds is None
        else dataclasses.replace(job, seconds=job.seconds * at_a_time, at_most=True)
        for job in jobs
    ]


def parse_duration(text: str, what: str = "time limit") -> float:
    """Seconds of "5400", "90m", "3h", "2h30m" or "45s" (`what`: the setting, for the error)."""
    if re.fullmatch(r"\d+(\.\d+)?", text):
        return float(text)
    parts = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:(\d+)s)?", text)
    if not text or parts is None:
        raise ValueError(f"{what} {text!r}: give seconds, or e.g. 90m, 3h, 2h30m")
    h, m, s = (int(p or 0) for p in parts.groups())
    return 3600.0 * h + 60.0 * m + s


def overrides(settings: list[str]) -> list[str]:
    """--set FIELD=VALUE items -> run.py's `--config.FIELD=VALUE`, each FIELD one a grid run
    chooses for itself and each VALUE of its field's type; otherwise a ValueError naming the
    valid ones."""
    from configs.base import get_config

    may = [f for f in report.grid_run_fields() if f not in ("seed", "seeds")]
    fields = lanes.flatten(get_config().to_dict())
    out = []
    for item in settings:
        field, eq, value = item.partition("=")
        ok = any(field == f or (f.endswith(".") and field.startswith(f)) for f in may)
        if not eq or not field or not ok or field not in fields:
            raise ValueError(
                f"--set {item!r}: give FIELD=VALUE with FIELD one a grid run may choose: "
                f"{', '.join(f + '*' if f.endswith('.') else f for f in may)} (the seeds come "
                "from the grid, the length from --frames; other fields make another experiment)"
            )
        kind = type(fields[field])
        try:
            if kind is bool and value.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            if kind in (int, float):
                kind(value)
        except ValueError:
            raise ValueError(
                f"--set {item!r}: {field} takes a {kind.__name__}, e.g. {fields[field]!r}"
            ) from None
        out.append(f"--config.{field}={value}")
    return out


def exit_code(rows: list[dict], stopping: str) -> int:
    """The queue's exit status (see the module docstring) from its rows and why it stopped."""
    if stopping in signal.Signals.__members__:
        return 128 + signal.Signals[stopping]
    if any(r["state"] in ("failed", "killed", "failed to start") for r in rows):
        return 1
    return 0 if all(r["state"] == "finished" for r in rows) else EX_TEMPFAIL


def _stamp(start: float) -> str:
    s = int(time.monotonic() - start)
    return f"[{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}]"


class Queue:
    """Runs `jobs` (`report.Job`), one per free slot, each as `command(job)` (an argv; pinned to
    its slot's cores with taskset where it exists) in `cwd`, its console in log_dir/NAME.out,
    until all ended, the time limit passed or a signal came (then the running ones get SIGTERM
    and are waited for). Within `start_margin` of the time limit no job starts; with `fit`, a
    job with `seconds` starts only where START_MARGIN_S + FIT_FACTOR x seconds are left (one
    without, start_margin), and the first queued job that fits goes first."""

    def __init__(
        self, jobs, places, command, log_dir, cwd=REPO, time_limit=None, poll=1.0,
        start_margin=START_MARGIN_S, kill_after=KILL_AFTER_S, fit=False,
    ):  # fmt: skip
        self.jobs, self.places, self.command = list(jobs), list(places), command
        self.log_dir, self.cwd, self.time_limit, self.poll = log_dir, cwd, time_limit, poll
        self.start_margin, self.kill_after, self.fit = start_margin, kill_after, fit
        self.stopping = ""  # why the queue stops early: "" while it goes on
        self._signals = 0  # signals received, each forwarded to the runs

    def _on_signal(self, signum, _frame) -> None:
        self.stopping = self.stopping or signal.Signals(signum).name
        self._signals += 1

    def _start(self, job, slot: Slot) -> subprocess.Popen:
        argv = list(self.command(job))
        if shutil.which("taskset"):
            argv = ["taskset", "-c", _ranges(slot.cores), *argv]
        self.log_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_dir / f"{job.name}.out", "ab") as console:
            return subprocess.Popen(
                argv,
                cwd=self.cwd,
                env=slot.env(),
                stdin=subprocess.DEVNULL,
                stdout=console,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # a terminal's Ctrl-C reaches the queue only
            )

    def run(self, echo=print) -> list[dict]:
        """A row per job, in order: job, where, state (finished, stopped, failed, killed, failed
        to start, not started), rc and seconds."""
        start = time.monotonic()
        queued, free = list(enumerate(self.jobs)), list(self.places)
        running = {}  # Popen -> (index, slot, start)
        rows = [{"job": job.name, "where": "-", "state": "not started"} for job in self.jobs]
        previous = {sig: signal.signal(sig, self._on_signal) for sig in SIGNALS}
        forwarded, stopped_at = 0, None

        def next_job() -> int | None:
            """The place in `queued` of the job to start now, if any (None once stopping)."""
            left = math.inf
            if self.time_limit is not None:
                left = self.time_limit - (time.monotonic() - start)
                if left <= 0:
                    self.stopping = self.stopping or "the time limit"
            for k, (_, job) in enumerate([] if self.stopping else queued):
                need = self.start_margin
                if self.fit and job.seconds is not None:
                    need = time_needed(job.seconds)
                if left >= need:
                    return k
                if not self.fit:
                    break
            return None

        try:
            while running or (queued and next_job() is not None):
                while queued and free and (k := next_job()) is not None:
                    (i, job), slot = queued.pop(k), free.pop(0)
                    rows[i].update(where=str(slot))
                    try:
                        running[self._start(job, slot)] = (i, slot, time.monotonic())
                    except OSError as e:
                        rows[i].update(state="failed to start", error=str(e))
                        echo(f"{_stamp(start)} {job.name} failed to start: {e}")
                        free.append(slot)
                        continue
                    rows[i]["state"] = "running"
                    echo(f"{_stamp(start)} {job.name} started on {slot}; {len(queued)} queued")
                next_job()  # the time limit may have passed
                if self.stopping and (forwarded < max(1, self._signals)):
                    echo(f"{_stamp(start)} stopping on {self.stopping}: SIGTERM to the runs")
                    for process in running:
                        process.send_signal(signal.SIGTERM)
                    forwarded = max(1, self._signals)
                    stopped_at = stopped_at or time.monotonic()
                if stopped_at and time.monotonic() - stopped_at > self.kill_after:
                    for process in running:
                        process.kill()
                time.sleep(self.poll)
                for process in [p for p in running if p.poll() is not None]:
                    i, slot, began = running.pop(process)
                    rc, seconds = process.returncode, round(time.monotonic() - began)
                    killed = rc == -signal.SIGKILL and stopped_at is not None
                    state = (
                        "finished" if rc == 0
                        else "stopped" if rc in STOPPED
                        else "killed" if killed
                        else "failed"
                    )  # fmt: skip
                    rows[i].update(state=state, rc=rc, seconds=seconds)
                    echo(f"{_stamp(start)} {self.jobs[i].name} {state} (rc {rc}, {seconds:,} s)")
                    free.append(slot)
            if queued and not self.stopping:
                names = ", ".join(job.name for _, job in queued)
                echo(f"{_stamp(start)} not started, too long for the time left: {names}")
        finally:  # an error here leaves no run behind
            for process in running:
                process.send_signal(signal.SIGTERM)
            for process in running:
                try:
                    process.wait(self.kill_after)
                except subprocess.TimeoutExpired:
                    process.kill()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return rows


def _workdirs(runs, root: pathlib.Path) -> list:
    """The runs named and every run under root."""
    return [*runs, *(p.parent for p in sorted(root.glob("*/config.json")))]


def time_needed(seconds: float) -> float:
    """What `--start-margin auto` asks to be left of the time limit for a job of that length."""
    return START_MARGIN_S + FIT_FACTOR * seconds


def overrun_warning(jobs: list[report.Job], limit: float, given: str) -> str | None:
    """A line naming the jobs whose length (or bound) would not fit in the time limit (`given`
    as the user wrote it) by `auto`'s rule, or None: with a fixed --start-margin the queue starts
    them anyway and stops them short at the limit."""
    longer = [job for job in jobs if job.seconds is not None and time_needed(job.seconds) > limit]
    if not longer:
        return None
    named = ", ".join(
        f"{job.name} ({'at most ' if job.at_most else ''}~{job.seconds / 60:.0f} min)"
        for job in longer
    )
    return (
        f"warning: {len(longer)} of the runs may not finish within the time limit of {given} "
        f"and be stopped short: {named}; with --start-margin auto only the runs that fit start"
    )


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
    parser.add_argument(
        "--tasks", nargs="+", default=["walker", "cup", "finger"], help=report.TASKS_HELP
    )
    parser.add_argument("--methods", nargs="+", default=["dear", "sear", "ted", "drqv2"])
    parser.add_argument("--seeds", type=report.positive_int, default=3, help="seeds per cell")
    parser.add_argument(
        "--frames", type=report.positive_int, default=1_000_000, help="frames per seed"
    )
    parser.add_argument("--seeds-per-run", type=int, default=1, help=report.SEEDS_PER_RUN_HELP)
    parser.add_argument("--set", action="append", default=[], help="FIELD=VALUE for new runs")
    parser.add_argument("--time-limit", default=None, help="e.g. 90m, 3h: then SIGTERM the runs")
    parser.add_argument(
        "--start-margin",
        default="60",
        help="no job starts this close to the time limit; auto[:MARGIN]: where its length fits",
    )
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="print the queue (lengths where known, their sum, those past --time-limit), run nothing",
    )
    args = parser.parse_args(argv)
    if str(REPO) not in sys.path:  # configs/, as run.py finds it
        sys.path.insert(0, str(REPO))
    root = pathlib.Path(args.root).resolve()
    try:
        limit = None if args.time_limit is None else parse_duration(args.time_limit)
        if limit is not None and limit <= 0:
            raise ValueError(f"time limit {args.time_limit!r}: give a time > 0, e.g. 90m")
        head, _, fallback = args.start_margin.partition(":")
        fit = head == "auto"
        margin = parse_duration(
            (fallback or str(START_MARGIN_S)) if fit else args.start_margin,
            "--start-margin (or auto, auto:MARGIN)",
        )
        extra = overrides(args.set)
        gpus = visible_gpus() if args.gpus is None else [g for g in args.gpus.split(",") if g]
        places = slots(gpus, args.per_gpu)
        taken = {p.name for p in root.iterdir()} if root.is_dir() else set()
        grid = report.grid_rows(
            _workdirs(args.runs, root), args.tasks, args.methods, args.seeds, args.frames, taken
        )
    except (FileNotFoundError, ValueError, KeyError) as e:
        parser.error(str(e))
    try:
        jobs = report.grid_jobs(grid, args.frames, str(root), extra, args.seeds_per_run)
        jobs = shared_gpu_lengths(jobs, args.per_gpu)
    except ValueError as e:
        parser.error(str(e))
    if not jobs:
        print("The grid is complete: no seed-run is missing.")
    else:
        print(f"{len(jobs)} runs to complete the grid, {len(places)} at a time:")
    for job in jobs:
        at_most = "at most " if job.at_most else ""
        length = (
            "" if job.seconds is None else f" ({at_most}~{job.seconds / 60:.0f} min of training)"
        )
        print(f"  {job.name}{length}: python run.py {shlex.join(job.args)}")
    known = [job.seconds for job in jobs if job.seconds is not None]
    if known:
        some = f"{len(known)} of the {len(jobs)} runs (no length known for the rest)"
        runs = f"{len(jobs)} runs" if len(known) == len(jobs) else some
        at_most = "at most " if any(job.at_most for job in jobs) else ""
        shared = f", times {args.per_gpu}: {args.per_gpu} per GPU" if args.per_gpu > 1 else ""
        print(
            f"{at_most}~{sum(known) / 3600:.1f} h of training in all, {runs}, at the pace of the "
            f"runs named on their own devices{shared}"
        )
    if limit is not None and not fit:
        warning = overrun_warning(jobs, limit, args.time_limit)
        if warning:
            print(warning)
    if args.dry_run or not jobs:
        return None
    queue = Queue(
        jobs,
        places,
        lambda job: [sys.executable, str(REPO / "run.py"), *job.args],
        root,
        time_limit=limit,
        start_margin=margin,
        fit=fit,
    )
    rows = queue.run()
    columns = ["job", "where", "state", "rc", "seconds"]
    print(format_table(columns, [[r.get(c, "-") for c in columns] for r in rows]))
    done = _workdirs(args.runs, root)
    print(
        report.grid_table(
            done, args.tasks, args.methods, args.seeds, args.frames, args.seeds_per_run, args.root
        )
    )
    code = exit_code(rows, queue.stopping)
    if code:
        sys.exit(code)
    return rows


if __name__ == "__main__":
    main()
