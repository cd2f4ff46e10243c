"""`python -m dear_jax.grid`: the grid's missing seed-runs as a queue over GPUs. The queue runs
real processes here (a small Python script in place of run.py) and checks where and when each
ran, what it was given, and that a time limit or a signal stops the runs with SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time

import pytest
from test_outputs import paper_run

from dear_jax import grid, report

# A job: records its GPU, cores and times in OUT/NAME.json; sleeps SECONDS, or until SIGTERM
# (SECONDS < 0), which it records and answers with exit 143, as run.py does after its checkpoint.
JOB = """
import json, os, signal, sys, time
name, out, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
record = {"gpu": os.environ["CUDA_VISIBLE_DEVICES"], "cores": sorted(os.sched_getaffinity(0)),
          "start": time.time()}
def stop(*_):
    record.update(end=time.time(), sigterm=True)
    open(os.path.join(out, name + ".json"), "w").write(json.dumps(record))
    sys.exit(143)
signal.signal(signal.SIGTERM, stop)
open(os.path.join(out, name + ".started"), "w").close()
end = time.time() + (seconds if seconds >= 0 else 60)
while time.time() < end:
    time.sleep(0.01)
record.update(end=time.time(), sigterm=False)
open(os.path.join(out, name + ".json"), "w").write(json.dumps(record))
"""


def _queue(tmp_path, names, places, seconds, **kwargs):
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    jobs = [report.Job(name, ()) for name in names]

    def command(job):
        return [sys.executable, "-c", JOB, job.name, str(out), str(seconds)]

    queue = grid.Queue(jobs, places, command, tmp_path / "consoles", poll=0.02, **kwargs)
    return queue, out


def _records(out, names) -> dict:
    return {
        n: json.loads((out / f"{n}.json").read_text())
        for n in names
        if (out / f"{n}.json").exists()
    }


def test_the_jobs_resume_stopped_runs_then_start_missing_seeds_task_by_task(tmp_path):
    """Stopped runs with a checkpoint come first, resumed in their workdirs; then a seed-run per
    missing seed, task by task, each task's methods taking turns; `report grid` prints the same
    commands; --set adds fields to the new seed-runs only."""
    done = [
        paper_run(tmp_path / "old" / "w_dear_s0", "walker,dear", 0, 1_000_000),
        paper_run(tmp_path / "old" / "w_dear_s1", "walker,dear", 1, 400_000, progress=False),
        paper_run(tmp_path / "old" / "c_sear_s0", "cup,sear", 0, 1_000_000),
    ]
    (done[1] / "checkpoints").mkdir()
    cells = report.grid_rows(done, ["walker", "cup"], ["dear", "sear"], seeds=2)
    extra = grid.overrides(["envs_per_seed=16", "agent.compute_dtype=bfloat16"])
    jobs = report.grid_jobs(cells, 1_000_000, "runs", extra)
    assert [job.name for job in jobs] == [
        "w_dear_s1",  # the resume: it brings walker dear's second seed
        "walker_sear_s0",
        "walker_sear_s1",
        "cup_dear_s0",  # cup: each method's first seed, then the second
        "cup_sear_s1",
        "cup_dear_s1",
    ]
    assert jobs[0].args == (  # restarted with what it chose, resumable fields included
        "--config",
        "configs/paper.py:walker,dear",
        "--config.progress=False",
        "--config.seed=1",
        "--config.seeds=1",
        "--workdir",
        str(done[1].resolve()),
    )
    assert jobs[1].args == (
        "--config",
        "configs/paper.py:walker,sear",
        "--config.seed=0",
        "--config.seeds=1",
        "--config.envs_per_seed=16",
        "--config.agent.compute_dtype=bfloat16",
        "--workdir",
        "runs/walker_sear_s0",
    )
    printed = report.grid_table(done, ["walker", "cup"], ["dear", "sear"], seeds=2).splitlines()
    plain = report.grid_jobs(cells, 1_000_000)
    assert [line for line in printed if line.startswith("python run.py")] == [
        "python run.py " + " ".join(job.args) for job in plain
    ]
    # A cell with its seeds resumes none of its stopped runs.
    full = report.grid_rows(done, ["walker"], ["dear"], seeds=1)
    assert full["cells"][0]["resume"] and report.grid_jobs(full, 1_000_000) == []
    # At 2M frames cup SEAR's seed is short (without a checkpoint: not resumed), and each new
    # run is told the length.
    cup = report.grid_rows(done, ["cup"], ["sear"], seeds=2, frames=2_000_000)
    longer = report.grid_jobs(cup, 2_000_000)
    assert [job.name for job in longer] == ["cup_sear_s1", "cup_sear_s2"]
    assert "--config.total_frames=2000000" in longer[0].args


def test_each_slot_runs_one_job_at_a_time_on_its_gpu_and_cores(tmp_path):
    """Five jobs on two GPUs, one at a time on each: every job runs once, with its slot's GPU
    and cores, a slot's jobs one after the other, both slots busy at once."""
    places = grid.slots(["3", "5"], per_gpu=1)
    cores = sorted(os.sched_getaffinity(0))
    assert [p.gpu for p in places] == ["3", "5"]
    assert sorted(c for p in places for c in p.cores) == cores[: len(places[0].cores) * 2]
    names = [f"job{i}" for i in range(5)]
    queue, out = _queue(tmp_path, names, places, seconds=1.0)
    rows = queue.run(echo=lambda line: None)
    assert [(r["job"], r["state"], r["rc"]) for r in rows] == [(n, "finished", 0) for n in names]
    records = _records(out, names)
    assert len(records) == 5
    for place in places:
        mine = sorted(
            (r for r in records.values() if r["gpu"] == place.gpu), key=lambda r: r["start"]
        )
        assert mine and all(r["cores"] == list(place.cores) for r in mine)
        assert all(a["end"] <= b["start"] for a, b in zip(mine, mine[1:]))  # one at a time
    first = [records["job0"], records["job1"]]
    assert first[0]["gpu"] != first[1]["gpu"]
    assert max(r["start"] for r in first) < min(r["end"] for r in first)  # side by side
    assert (tmp_path / "consoles" / "job4.out").exists()


def test_the_time_limit_stops_the_runs_with_sigterm_and_starts_no_more(tmp_path):
    names = ["a", "b", "c"]
    queue, out = _queue(tmp_path, names, grid.slots([], per_gpu=2), seconds=-1, time_limit=1.0)
    began = time.monotonic()
    rows = queue.run(echo=lambda line: None)
    assert time.monotonic() - began < 30
    assert queue.stopping == "the time limit"
    assert [(r["job"], r["state"], r.get("rc")) for r in rows] == [
        ("a", "stopped", 143),
        ("b", "stopped", 143),
        ("c", "not started", None),
    ]
    records = _records(out, names)
    assert set(records) == {"a", "b"} and all(r["sigterm"] for r in records.values())
    assert all(r["gpu"] == "" for r in records.values())  # no GPU: on the CPU


def test_a_sigterm_to_the_queue_reaches_its_runs(tmp_path):
    names = ["a", "b"]
    queue, out = _queue(tmp_path, names, grid.slots([], per_gpu=1), seconds=-1)

    def terminate():  # once the first job is up, as a scheduler's SIGTERM would come
        while not (out / "a.started").exists():
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=terminate, daemon=True).start()
    before = signal.getsignal(signal.SIGTERM)
    rows = queue.run(echo=lambda line: None)
    assert queue.stopping == "SIGTERM"
    assert [(r["state"], r.get("rc")) for r in rows] == [("stopped", 143), ("not started", None)]
    assert _records(out, names)["a"]["sigterm"]
    assert signal.getsignal(signal.SIGTERM) == before  # the handler is given back


def test_bad_settings_are_refused_by_name(tmp_path, capsys):
    assert grid.parse_duration("2h30m") == 9000 and grid.parse_duration("90") == 90
    with pytest.raises(ValueError, match="time limit '3 hours': give seconds, or e.g. 90m"):
        grid.parse_duration("3 hours")
    assert grid.overrides(["replay.capacity=1000", "progress=False"]) == [
        "--config.replay.capacity=1000",
        "--config.progress=False",
    ]
    for bad in ["agent.beta=2", "seed=4", "total_frames=10", "envs_per_seed"]:
        with pytest.raises(ValueError, match="FIELD one a grid run may choose: envs_per_seed"):
            grid.overrides([bad])
    with pytest.raises(ValueError, match="--per-gpu must be at least 1"):
        grid.slots(["0"], per_gpu=0)
    with pytest.raises(SystemExit):
        grid.main(["--root", str(tmp_path), "--set", "agent.alpha=0"])
    assert "--set 'agent.alpha=0'" in capsys.readouterr().err


def test_a_dry_run_prints_the_queue_of_the_runs_under_root(tmp_path, capsys):
    """The runs under --root count: a finished one is skipped, a stopped one resumed."""
    root = tmp_path / "runs"
    paper_run(root / "walker_dear_s0", "walker,dear", 0, 1_000_000)
    stopped = paper_run(root / "walker_dear_s1", "walker,dear", 1, 10_000)
    (stopped / "checkpoints").mkdir()
    grid.main(
        ["--root", str(root), "--tasks", "walker", "--methods", "dear", "--gpus", "0", "--dry-run"]
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("2 runs to complete the grid, 1 at a time")
    resume = "  walker_dear_s1: python run.py --config configs/paper.py:walker,dear"
    assert lines[1].startswith(resume) and lines[1].endswith(f"--workdir {stopped.resolve()}")
    assert lines[2].endswith(f"--workdir {root.resolve()}/walker_dear_s2")  # the third seed
