"""`python -m dear_jax.grid`: the grid's missing seed-runs as a queue over GPUs. The queue runs
real processes here (a small Python script in place of run.py) and checks where and when each
ran, what it was given, and that a time limit or a signal stops the runs with SIGTERM."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time

import pytest
from test_outputs import REPO, paper_run

from dear_jax import grid, report, summary

# A job: records its GPU, memory share, cores and times in OUT/NAME.json; sleeps SECONDS, or
# until SIGTERM (SECONDS = -1), which it records and answers with exit 143, as run.py does after
# its checkpoint; SECONDS = -2: fails at once (exit 1).
JOB = """
import json, os, signal, sys, time
name, out, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
if seconds == -2:
    sys.exit(1)
record = {"gpu": os.environ["CUDA_VISIBLE_DEVICES"], "cores": sorted(os.sched_getaffinity(0)),
          "memory": os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION"), "start": time.time()}
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
    """A queue of JOBs named `names`; `seconds`: one for all, or a dict by name."""
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    jobs = [report.Job(name, ()) for name in names]

    def command(job):
        wait = seconds[job.name] if isinstance(seconds, dict) else seconds
        return [sys.executable, "-c", JOB, job.name, str(out), str(wait)]

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
    # The queue's closing table names the new runs' workdirs under its --root.
    elsewhere = report.grid_table(done, ["walker"], ["sear"], seeds=2, root="mine").splitlines()
    assert any(line.endswith("--workdir mine/walker_sear_s0") for line in elsewhere)
    # A cell with its seeds resumes none of its stopped runs.
    full = report.grid_rows(done, ["walker"], ["dear"], seeds=1)
    assert full["cells"][0]["short"] and report.grid_jobs(full, 1_000_000) == []
    # A stopped run brings all its seeds, one config.seed counts once, the furthest resumes; and
    # resumed workdirs of one name (in two folders) get names of their own.
    three = paper_run(tmp_path / "old" / "c_dear_s0", "cup,dear", 0, 300_000, seeds=3)
    again = paper_run(tmp_path / "older" / "c_dear_s0", "cup,dear", 0, 100_000, seeds=3)
    other = paper_run(tmp_path / "older" / "c_dear_s5", "cup,dear", 5, 10_000)
    for run in (three, again, other):
        (run / "checkpoints").mkdir()
    cup = report.grid_rows([three, again, other], ["cup"], ["dear"], seeds=3)
    assert [args[-1] for args in cup["cells"][0]["resume"]] == [str(three.resolve())]
    assert cup["cells"][0]["next_seeds"] == []
    cup = report.grid_rows([three, again, other], ["cup"], ["dear"], seeds=4)
    assert [args[-1] for args in cup["cells"][0]["resume"]] == [
        str(three.resolve()),
        str(other.resolve()),
    ]
    named = report.grid_jobs(
        report.grid_rows([three, other], ["cup"], ["dear"], seeds=5), 1_000_000
    )
    assert [job.name for job in named] == ["c_dear_s0", "c_dear_s5", "cup_dear_s1"]
    twin = paper_run(tmp_path / "older" / "c_dear_s7", "cup,dear", 7, 10_000)
    twin2 = paper_run(tmp_path / "old" / "c_dear_s7", "cup,dear", 8, 10_000)
    for run in (twin, twin2):
        (run / "checkpoints").mkdir()
    named = report.grid_jobs(report.grid_rows([twin, twin2], ["cup"], ["dear"], seeds=2), 1_000_000)
    assert [job.name for job in named] == ["c_dear_s7_1", "c_dear_s7_2"]
    # A new run's workdir name already taken under the root is skipped.
    taken = report.grid_rows([], ["cup"], ["dear"], seeds=2, taken={"cup_dear_s0"})
    assert taken["cells"][0]["next_seeds"] == [1, 2]
    # At 2M frames cup SEAR's seed is short (without a checkpoint: not resumed), and each new
    # run is told the length.
    cup = report.grid_rows(done, ["cup"], ["sear"], seeds=2, frames=2_000_000)
    longer = report.grid_jobs(cup, 2_000_000)
    assert [job.name for job in longer] == ["cup_sear_s1", "cup_sear_s2"]
    assert "--config.total_frames=2000000" in longer[0].args
    # Two missing seeds per seed-run, as lanes of one process: walker SEAR's three seeds take a
    # run of two and one of one (each its own config.seed); walker DEAR's resume brings one of
    # its two missing seeds, so one seed-run of one lane starts.
    three = report.grid_rows(done, ["walker"], ["dear", "sear"], seeds=3)
    paired = report.grid_jobs(three, 1_000_000, seeds_per_run=2)
    assert [(job.name, job.args[2:4]) for job in paired[1:]] == [
        ("walker_dear_s2", ("--config.seed=2", "--config.seeds=1")),
        ("walker_sear_s0", ("--config.seed=0", "--config.seeds=2")),
        ("walker_sear_s1", ("--config.seed=1", "--config.seeds=1")),
    ]
    assert paired[0].name == "w_dear_s1"
    with pytest.raises(ValueError, match="seeds per run must be at least 1, got 0"):
        report.grid_jobs(three, 1_000_000, seeds_per_run=0)


def test_a_run_stopped_at_its_last_frame_is_resumed_for_its_closing_evaluation(tmp_path):
    """A seed-run stopped in its last iteration (the grid's time limit, say) reached its frames
    but not its closing evaluation (train._finished): with checkpoints it is resumed, its replay
    kept or not (nothing is left to train); without them (a copy of its logs) it counts done."""

    def stopped(name, seed, **fields):
        run = paper_run(tmp_path / name, "cup,dear", seed, 1_000_000, **fields)
        (run / "summary.json").write_text(
            json.dumps({"frames_per_seed": 1_000_000, "stopped": "SIGTERM"})
        )
        return run

    kept, no_replay, copied = (
        stopped("kept", 0),
        stopped("no_replay", 1, **{"replay.disk": False}),
        stopped("copied", 2),
    )
    for run in (kept, no_replay):
        (run / "checkpoints").mkdir()
    cells = report.grid_rows([kept, no_replay, copied], ["cup"], ["dear"], seeds=3)
    (cell,) = cells["cells"]
    assert cell["done"] == [f"{tmp_path.name}/copied"] and cell["seeds_done"] == 1
    assert sorted(args[-1] for args in cell["resume"]) == sorted(
        str(r.resolve()) for r in (kept, no_replay)
    )
    assert f"{tmp_path.name}/kept (1,000,000, before its closing evaluation)" in cell["short"]
    assert cell["next_seeds"] == []


def test_new_seed_runs_choose_what_the_cells_finished_runs_chose_alike(tmp_path):
    """A cell's finished runs all in bf16 with 16 envs per seed: its new seed-runs are too (and
    pool with them in `report table`), unless the queue's --set says otherwise; a choice the
    finished runs differ on is left to the cell's config."""
    fast = {"agent.compute_dtype": "bfloat16", "envs_per_seed": 16}
    done = [
        paper_run(tmp_path / "w_ted_s0", "walker,ted", 0, 1_000_000, **fast),
        paper_run(tmp_path / "w_ted_s1", "walker,ted", 1, 1_000_000, **fast),
        paper_run(tmp_path / "w_sear_s0", "walker,sear", 0, 1_000_000, **fast),
        paper_run(
            tmp_path / "w_sear_s1", "walker,sear", 1, 1_000_000, **{**fast, "envs_per_seed": 8}
        ),
        # Another experiment: sampled by episode, it brings the ted cell no third seed.
        paper_run(
            tmp_path / "w_ted_s2",
            "walker,ted",
            2,
            1_000_000,
            **fast,
            **{"replay.sampling": "episode"},
        ),
    ]
    cells = report.grid_rows(done, ["walker"], ["ted", "sear"], seeds=3)
    ted, sear = report.grid_jobs(cells, 1_000_000)
    assert ted.args[4:6] == ("--config.agent.compute_dtype=bfloat16", "--config.envs_per_seed=16")
    assert sear.args[4:5] == ("--config.agent.compute_dtype=bfloat16",)
    assert not [a for a in sear.args if a.startswith("--config.envs_per_seed")]
    ted, _ = report.grid_jobs(cells, 1_000_000, overrides=["--config.envs_per_seed=32"])
    assert [a for a in ted.args if "envs_per_seed" in a] == ["--config.envs_per_seed=32"]


def test_slots_split_the_cores_and_share_a_gpus_memory(monkeypatch):
    cores = sorted(os.sched_getaffinity(0))
    two = grid.slots(["3", "5"], per_gpu=1)
    assert [(p.gpu, p.memory_fraction) for p in two] == [("3", None), ("5", None)]
    assert [c for p in two for c in p.cores] == (cores if len(cores) > 1 else cores * 2)
    many = grid.slots(["0", "1"], per_gpu=3)  # more slots than cores, on a small machine
    assert [p.gpu for p in many] == ["0", "0", "0", "1", "1", "1"]
    assert {c for p in many for c in p.cores} == set(cores)  # every core serves
    assert all(len(p.cores) >= 1 and p.memory_fraction == 0.3 for p in many)
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    assert many[0].env()["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.30"
    # each job's summary records how many trained beside it (`summary.runs_per_gpu`)
    monkeypatch.setenv(summary.RUNS_PER_GPU_ENV, "7")  # the queue's own setting wins
    assert [many[0].env()[summary.RUNS_PER_GPU_ENV], two[0].env()[summary.RUNS_PER_GPU_ENV]] == [
        "3",
        "1",
    ]
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.5")  # the caller's share is kept
    assert many[0].env()["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.5"
    assert grid.slots([], per_gpu=2)[0].env()["CUDA_VISIBLE_DEVICES"] == ""
    assert str(grid.Slot("2", (0, 1, 2, 5))) == "GPU 2, cores 0-2,5"


def test_each_slot_runs_one_job_at_a_time_on_its_gpu_and_cores(tmp_path):
    """Five jobs on two GPUs, one at a time on each (a failing one among them): every job runs
    once, with its slot's GPU and cores, a slot's jobs one after the other, both slots started
    at once; a job that fails is said to."""
    places = grid.slots(["3", "5"], per_gpu=1)
    names = [f"job{i}" for i in range(5)]
    lines = []
    queue, out = _queue(tmp_path, names, places, seconds={**dict.fromkeys(names, 0.3), "job2": -2})
    rows = queue.run(echo=lines.append)
    assert [(r["job"], r["state"], r["rc"]) for r in rows] == [
        (n, "failed" if n == "job2" else "finished", 1 if n == "job2" else 0) for n in names
    ]
    assert grid.exit_code(rows, queue.stopping) == 1
    assert [line.split()[1:3] for line in lines[:2]] == [["job0", "started"], ["job1", "started"]]
    records = _records(out, names)
    assert set(records) == set(names) - {"job2"}
    for place in places:
        mine = sorted(
            (r for r in records.values() if r["gpu"] == place.gpu), key=lambda r: r["start"]
        )
        assert mine and all(r["cores"] == list(place.cores) for r in mine)
        assert all(a["end"] <= b["start"] for a, b in zip(mine, mine[1:]))  # one at a time
    assert records["job0"]["gpu"] != records["job1"]["gpu"]
    assert (tmp_path / "consoles" / "job4.out").exists()


def _when_started(out, names, then):
    """Calls `then` from a thread once every job of `names` is up (its SIGTERM handler set)."""

    def wait():
        while not all((out / f"{n}.started").exists() for n in names):
            time.sleep(0.01)
        then()

    threading.Thread(target=wait, daemon=True).start()


def test_the_time_limit_stops_the_runs_with_sigterm_and_starts_no_more(tmp_path):
    names = ["a", "b", "c"]
    queue, out = _queue(tmp_path, names, grid.slots([], per_gpu=2), seconds=-1)
    _when_started(out, ["a", "b"], lambda: setattr(queue, "time_limit", 0.0))  # it passes
    rows = queue.run(echo=lambda line: None)
    assert queue.stopping == "the time limit"
    assert [(r["job"], r["state"], r.get("rc")) for r in rows] == [
        ("a", "stopped", 143),
        ("b", "stopped", 143),
        ("c", "not started", None),
    ]
    assert grid.exit_code(rows, queue.stopping) == grid.EX_TEMPFAIL
    records = _records(out, names)
    assert set(records) == {"a", "b"} and all(r["sigterm"] for r in records.values())
    assert all(r["gpu"] == "" and r["memory"] is None for r in records.values())  # on the CPU
    # Within the start margin of the limit no job starts.
    margin = _queue(tmp_path, ["d"], grid.slots([], per_gpu=1), seconds=0, time_limit=30)[0]
    assert [r["state"] for r in margin.run(echo=lambda line: None)] == ["not started"]


def test_a_jobs_length_comes_from_its_cells_finished_runs_of_as_many_lanes(tmp_path):
    """A new seed-run's seconds: the grid's frames at the median pace of its cell's runs that
    reached them with as many lanes (without logs, their wall clock per frame), else of its
    task and method's in other settings; none without such runs. With logs, the pace is the
    training's own (`report evals`' training time between evaluations) and its periodic
    checkpoints' (not for a seed-run that saves none): a shipped 1M finger run's."""
    runs = []
    for i, (frames, wall, seeds) in enumerate(
        [(1_000_000, 900.0, 1), (1_000_000, 1200.0, 1), (1_000_000, 600.0, 1),
         (400_000, 100.0, 1), (1_000_000, 3000.0, 3)]
    ):  # fmt: skip
        run = paper_run(tmp_path / f"f_ted_{i}", "finger,ted", i, frames, seeds)
        (run / "summary.json").write_text(json.dumps({"frames_per_seed": frames, "wall_s": wall}))
        runs.append(run)
    cells = report.grid_rows(runs, ["finger"], ["ted", "drqv2"], seeds=9)
    jobs = report.grid_jobs(cells, 500_000)
    ted = [job.seconds for job in jobs if job.name.startswith("finger_ted")]
    assert ted == [pytest.approx(450.0)] * 3  # 900 s per 1M frames, at 500k frames
    assert {job.seconds for job in jobs if job.name.startswith("finger_drqv2")} == {None}
    three = report.grid_jobs(cells, 1_000_000, seeds_per_run=3)
    assert [job.seconds for job in three if "ted" in job.name] == [pytest.approx(3000.0)]
    assert not any(job.at_most for job in [*jobs, *three])
    # No runs of as many lanes: at most the smallest bound from the others. Three missing seeds
    # as 2 + 1 lanes: 2 lanes take no longer than 2x one lane's 900 s nor the 3 lanes' 3,000.
    two = report.grid_jobs(cells, 1_000_000, seeds_per_run=2)
    two = [(job.seconds, job.at_most) for job in two if "ted" in job.name]
    assert two == [(pytest.approx(1800.0), True), (pytest.approx(900.0), False)]
    # Five missing as 5 lanes: 5x 900 (4,500) against 5/3 x 3,000 (5,000).
    eleven = report.grid_rows(runs, ["finger"], ["ted"], seeds=11)
    (five,) = report.grid_jobs(eleven, 1_000_000, seeds_per_run=5)
    assert (five.seconds, five.at_most) == (pytest.approx(4500.0), True)
    # A cell without such runs goes by its task and method's runs in other settings (here the
    # paper's, for the full suite's cell), until it has its own.
    (job,) = report.grid_jobs(report.grid_rows(runs, ["finger,medium-full"], ["ted"], 1), 500_000)
    assert job.seconds == pytest.approx(450.0)
    full = paper_run(tmp_path / "f_ted_full", "finger,ted,medium-full", 0, 1_000_000)
    (full / "summary.json").write_text(json.dumps({"frames_per_seed": 1_000_000, "wall_s": 2e3}))
    (job,) = report.grid_jobs(
        report.grid_rows([*runs, full], ["finger,medium-full"], ["ted"], 2), 500_000
    )
    assert job.seconds == pytest.approx(1000.0)
    shipped = REPO / "results" / "finger_paper_1m" / "finger_drqv2_s1"
    logged = tmp_path / "logged" / shipped.name
    shutil.copytree(shipped, logged)
    (row,) = report.eval_rows([logged])
    assert 6.0 < row["train_s"] < 8.0  # s per 10k frames; the run's wall clock gives 9.9
    (job,) = report.grid_jobs(report.grid_rows([logged], ["finger"], ["drqv2"], 2), 1_000_000)
    # its training's pace and its periodic checkpoints (108 s), not its waits for evaluations
    assert row["checkpoint_excess_s"] > 100
    assert job.seconds == pytest.approx(row["train_s"] * 100 + row["checkpoint_excess_s"])
    # A seed-run that saves no periodic checkpoints takes its training's pace alone.
    cells = report.grid_rows([logged], ["finger"], ["drqv2"], 2)
    off = ("--config.checkpoint_every_frames=100000", "--config.checkpoint_every_frames=0")
    (job,) = report.grid_jobs(cells, 1_000_000, overrides=off)
    assert job.seconds == pytest.approx(row["train_s"] * 100)
    (job,) = report.grid_jobs(cells, 1_000_000, overrides=off[::-1])
    assert job.seconds == pytest.approx(row["train_s"] * 100 + row["checkpoint_excess_s"])
    (job,) = report.grid_jobs(cells, 1_000_000, overrides=("--config.checkpoint_every_frames=00",))
    assert job.seconds == pytest.approx(row["train_s"] * 100)


def test_auto_start_margin_starts_the_jobs_that_fit_before_the_limit(tmp_path):
    """With `fit`, a job of known length starts only where a minute and 1.1x its seconds are
    left: a long job waits while a shorter one behind it starts, and is named at the end; a job
    of unknown length needs the start margin. Without `fit` the seconds count for nothing: the
    queue keeps its order."""
    names = ["long", "short", "unknown"]
    lengths = {"long": 100.0, "short": 10.0, "unknown": None}  # need 170, 71 and 5 s
    queue, out = _queue(tmp_path, names, grid.slots([], per_gpu=1), seconds=0, time_limit=100)
    queue.jobs = [report.Job(n, (), lengths[n]) for n in names]
    queue.start_margin, queue.fit = 5.0, True
    said = []
    rows = queue.run(echo=said.append)
    assert [(r["job"], r["state"]) for r in rows] == [
        ("long", "not started"),
        ("short", "finished"),
        ("unknown", "finished"),
    ]
    started = _records(out, ["short", "unknown"])
    assert started["short"]["start"] < started["unknown"]["start"]
    assert said[-1].endswith("not started, too long for the time left: long")
    assert grid.exit_code(rows, queue.stopping) == grid.EX_TEMPFAIL
    queue.fit = False
    (out / "short.json").unlink()
    rows = queue.run(echo=lambda line: None)
    assert [r["state"] for r in rows] == ["finished"] * 3
    started = _records(out, names)
    assert started["long"]["start"] < started["short"]["start"] < started["unknown"]["start"]


def test_a_sigterm_to_the_queue_reaches_its_runs(tmp_path):
    names = ["a", "b"]
    queue, out = _queue(tmp_path, names, grid.slots([], per_gpu=1), seconds=-1)

    # once the first job is up, as a scheduler's SIGTERM would come
    _when_started(out, ["a"], lambda: os.kill(os.getpid(), signal.SIGTERM))
    before = signal.getsignal(signal.SIGTERM)
    rows = queue.run(echo=lambda line: None)
    assert queue.stopping == "SIGTERM"
    assert [(r["state"], r.get("rc")) for r in rows] == [("stopped", 143), ("not started", None)]
    assert grid.exit_code(rows, queue.stopping) == 128 + signal.SIGTERM
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
    bad_ones = ["agent.beta=2", "seed=4", "total_frames=10", "envs_per_seed", "replay.bogus=1"]
    for bad in [*bad_ones, "replay.sampling=episode"]:
        with pytest.raises(ValueError, match="FIELD one a grid run may choose: envs_per_seed"):
            grid.overrides([bad])
    # A value of the wrong type is refused before any run would start and fail on it.
    for bad, kind in [("envs_per_seed=abc", "int"), ("progress=maybe", "bool")]:
        with pytest.raises(ValueError, match=f"takes a {kind}, e.g."):
            grid.overrides([bad])
    with pytest.raises(ValueError, match="--per-gpu must be at least 1"):
        grid.slots(["0"], per_gpu=0)
    with pytest.raises(SystemExit):
        grid.main(["--root", str(tmp_path), "--set", "agent.alpha=0"])
    assert "--set 'agent.alpha=0'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        grid.main(["--root", str(tmp_path), "--time-limit", "0"])
    assert "time limit '0': give a time > 0" in capsys.readouterr().err
    # No seeds or frames to reach would call any grid complete: refused, by the queue and the report.
    for main, flag in [(grid.main, "--seeds"), (grid.main, "--frames"), (report.main, "--seeds")]:
        args = ["grid", str(tmp_path)] if main is report.main else ["--root", str(tmp_path)]
        with pytest.raises(SystemExit):
            main([*args, flag, "0", *(["--dry-run"] if main is grid.main else [])])
        assert f"argument {flag}: must be >= 1, got 0" in capsys.readouterr().err


def test_a_complete_grid_says_so_and_starts_nothing(tmp_path, capsys):
    """Every seed of the cells asked for at the frames asked for: the queue says the grid is
    complete (no job listed, no training time) and returns without starting anything."""
    root = tmp_path / "runs"
    for seed in range(3):
        paper_run(root / f"walker_dear_s{seed}", "walker,dear", seed, 1_000_000)
    assert (
        grid.main(["--root", str(root), "--tasks", "walker", "--methods", "dear", "--gpus", "0"])
        is None
    )
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "The grid is complete: no seed-run is missing."
    assert "python run.py" not in out and "of training in all" not in out
    assert sorted(p.name for p in root.iterdir()) == [f"walker_dear_s{i}" for i in range(3)]


def test_a_dry_run_prints_the_queue_of_the_runs_under_root(tmp_path, capsys):
    """The runs under --root count: a finished one is skipped, a stopped one resumed. A new
    seed-run's length comes from the finished one; the total counts the runs of known length."""
    root = tmp_path / "runs"
    done = paper_run(root / "walker_dear_s0", "walker,dear", 0, 1_000_000)
    (done / "summary.json").write_text(json.dumps({"frames_per_seed": 1_000_000, "wall_s": 1.2e3}))
    stopped = paper_run(root / "walker_dear_s1", "walker,dear", 1, 10_000)
    (stopped / "checkpoints").mkdir()
    grid.main(
        ["--root", str(root), "--tasks", "walker", "--methods", "dear", "--gpus", "0"]
        + ["--time-limit", "3h", "--start-margin", "25m", "--dry-run"]
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("2 runs to complete the grid, 1 at a time")
    resume = "  walker_dear_s1: python run.py --config configs/paper.py:walker,dear"
    assert lines[1].startswith(resume) and lines[1].endswith(f"--workdir {stopped.resolve()}")
    assert lines[2].endswith(f"--workdir {root.resolve()}/walker_dear_s2")  # the third seed
    assert lines[2].startswith("  walker_dear_s2 (~20 min of training): python run.py")
    assert lines[3] == (
        "~0.3 h of training in all, 1 of the 2 runs (no length known for the rest), at the pace "
        "of the runs named on their own devices"
    )


def test_jobs_side_by_side_on_a_gpu_take_at_most_as_many_times_as_long(tmp_path, capsys):
    """With --per-gpu 2 a new seed-run's length is a bound, twice its length alone, for `auto`
    and in the queue printed; a job of unknown length stays unknown. The lengths alone go by
    runs that trained alone: one that trained beside another (its summary's runs_per_gpu) does
    not count."""
    root = tmp_path / "runs"
    done = paper_run(root / "walker_dear_s0", "walker,dear", 0, 1_000_000)
    (done / "summary.json").write_text(json.dumps({"frames_per_seed": 1_000_000, "wall_s": 1.2e3}))
    beside = paper_run(root / "walker_dear_s1", "walker,dear", 1, 1_000_000)
    shared = {"frames_per_seed": 1_000_000, "wall_s": 9e3, "runs_per_gpu": 2}
    (beside / "summary.json").write_text(json.dumps(shared))
    jobs = [report.Job("a", (), 600.0), report.Job("b", ())]
    assert grid.shared_gpu_lengths(jobs, 1) == jobs
    assert grid.shared_gpu_lengths(jobs, 3) == [
        report.Job("a", (), 1800.0, True),
        report.Job("b", ()),
    ]
    grid.main(
        ["--root", str(root), "--tasks", "walker", "--methods", "dear", "--gpus", "0"]
        + ["--per-gpu", "2", "--seeds", "3", "--dry-run"]
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "1 runs to complete the grid, 2 at a time:"
    assert lines[1].startswith("  walker_dear_s2 (at most ~40 min of training): python run.py")
    assert lines[2] == (
        "at most ~0.7 h of training in all, 1 runs, at the pace of the runs named on their own "
        "devices, times 2: 2 per GPU"
    )
    assert not any(line.startswith("warning") for line in lines)  # no time limit, no warning
    # A time limit shorter than a run's bound: with a fixed start margin the queue would start it
    # and stop it short, so the dry run says so; with `auto` the queue starts only what fits.
    base = ["--root", str(root), "--tasks", "walker", "--methods", "dear", "--gpus", "0"]
    base += ["--per-gpu", "2", "--seeds", "3", "--dry-run", "--time-limit", "30m"]
    grid.main([*base, "--start-margin", "60"])
    assert capsys.readouterr().out.splitlines()[-1] == (
        "warning: 1 of the runs may not finish within the time limit of 30m and be stopped "
        "short: walker_dear_s2 (at most ~40 min); with --start-margin auto only the runs that "
        "fit start"
    )
    grid.main([*base, "--start-margin", "auto"])
    assert "warning" not in capsys.readouterr().out
    grid.main([*base[:-1], "45m", "--start-margin", "60"])  # 60 s + 1.1 x 40 min fit
    assert "warning" not in capsys.readouterr().out
    # By `auto`'s rule (a minute plus 1.1x the length): 600 s needs 720 s; a job of unknown
    # length (a resumed one) is not named.
    jobs = [report.Job("a", (), 600.0), report.Job("b", ()), report.Job("c", (), 60.0)]
    assert grid.overrun_warning(jobs, 720.0, "12m") is None
    assert grid.overrun_warning(jobs, 719.0, "719").startswith(
        "warning: 1 of the runs may not finish within the time limit of 719 and be stopped "
        "short: a (~10 min);"
    )
