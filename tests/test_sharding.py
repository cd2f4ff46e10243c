"""Seeds split over devices (`config.devices`): the same run bit for bit, resumable across device
counts, arrays living where their seeds are, and splits that cannot work refused by name.

A CPU process has several devices only if an XLA flag says so before jax starts, so the runs
happen in one child process (this file run as a script) with 4 virtual CPU devices, and the
tests read what it wrote: checkpoints, logs and the placements it recorded. XLA:CPU's fusion
emitters are off in the child: on, they may fuse the per-seed code of a 2-seed program
differently from that of a 1-seed program, which then rounds differently after a few updates
(jax 0.10.2); off, a seed's code is the same on any split, which is what is checked here.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# conftest's flags; the split runs ("runs") at LLVM's default optimisation level: at level 0 a
# seed's code in a 2-seed program rounds differently from that of a 1-seed program (one ulp of an
# Adam moment after a few updates).
FLAGS = "--xla_force_host_platform_device_count=4 " + os.environ["XLA_FLAGS"]
RUNS_FLAGS = FLAGS.replace("--xla_backend_optimization_level=0", "")
CUT, END = 160, 200  # frames per seed: the first runs stop at CUT (updates start at 120)


def config(**overrides):
    """test_run's tiny config, evaluating and saving at CUT (where the first runs stop)."""
    from test_run import tiny_config

    # "loop": each seed's program is the same whatever seeds share its device (docs/design.md).
    overrides = {"agent.seed_axis": "loop", **overrides}
    return tiny_config(eval_every_frames=CUT, checkpoint_every_frames=CUT, **overrides)


def _where(tree) -> list:
    """The distinct (partition spec, device count) of the device leaves of `tree` that have an
    axis (all lead with the seeds axis); 0-d leaves are keys, checked on their own."""
    import jax

    leaves = [x for x in jax.tree.leaves(tree) if isinstance(x, jax.Array) and x.ndim]
    return sorted(
        {(str(getattr(x.sharding, "spec", None)), len(x.sharding.device_set)) for x in leaves}
    )


def _placements(run) -> dict:
    return {
        "agent": _where(run.carry.agent),
        "replay": _where(run.carry.buffer),
        "env": _where(run.carry.state),
        "timestep": _where(run.carry.ts),
        "returns": _where(run.carry.returns),
        "physics_threads": run.env.physics.threads,
        "key": sorted({(str(run.carry.key.sharding.spec), len(run.carry.key.sharding.device_set))})
        if run.mesh is not None
        else [],
    }


def _child(root: pathlib.Path) -> None:
    """The runs of this module, in a process with 4 devices; writes root/placements.json."""
    import jax
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from dear_jax import loop, train
    from envs import dmc
    from envs.physics import MjxPhysics

    assert len(jax.devices()) == 4, jax.devices()
    placements = []
    save = loop.Loop.save

    def recording_save(run, wall_s):  # every checkpoint: after the start and after resuming
        devices = 1 if run.mesh is None else run.mesh.size
        placements.append({"devices": devices, **_placements(run)})
        save(run, wall_s)

    loop.Loop.save = recording_save
    # Grouped by device count: the compiled programs of a process are those of its last mesh.
    train.train(config(total_frames=END), root / "whole")
    train.train(config(total_frames=CUT), root / "to_split")
    train.train(config(total_frames=CUT, devices=2), root / "from_split")
    train.train(config(total_frames=END, devices=2), root / "to_split")
    train.train(config(total_frames=END), root / "from_split")

    # MJX physics keeps each seed's state on its device (CPU runs use CPU physics).
    mesh = Mesh(np.array(jax.devices()), ("seeds",))
    task = dmc.TASKS["walker-walk"]
    model = task.physics_model()
    physics = MjxPhysics(
        model,
        task.make_reward(model),
        n_sub_steps=task.n_sub_steps(model),
        action_repeat=1,
        sharding=NamedSharding(mesh, P("seeds")),
    )
    shape = (4, 1)
    state = physics.init(np.tile(model.qpos0, shape + (1,)), np.zeros(shape + (model.nv,)))
    action = jax.device_put(np.full(shape + (model.nu,), 0.5, np.float32), physics.sharding)
    state, reward = physics.step(state, action)
    state = physics.where(np.array([[True], [False], [True], [False]]), state, state)
    mjx = {"state": _where(state), "reward": _where(reward)}
    (root / "placements.json").write_text(json.dumps({"runs": placements, "mjx": mjx}))


def _pallas_child(root: pathlib.Path) -> None:
    """act, add, learn and the evaluation step with the Pallas conv stacks and filter gradients
    (in Pallas' interpreter here) on one device, and with the 2 seeds split over 2 devices;
    writes each one's outputs and parameters to root/pallas_<devices>.npz."""
    import jax

    from dear_jax import devices, experiment, replay, update
    from dear_jax.programs import build_programs
    from envs.base import TimeStep

    pallas = {"agent.conv_stack": "pallas", "agent.filter_gradient": "pallas"}
    seeds, envs, action_dim, rows = 2, 2, 6, 12
    c = config(seeds=seeds, **pallas)
    acfg, hp = experiment.agent_config(c, action_dim), experiment.hparams(c)
    rng = np.random.default_rng(0)
    shape = (rows, seeds, envs)
    obs = rng.integers(0, 256, (seeds, envs, 84, 84, 9), np.uint8)
    steps = [
        TimeStep(
            obs=obs,
            frame=rng.integers(0, 256, (*shape[1:], 84, 84, 3), np.uint8),
            mask=rng.integers(0, 2, (*shape[1:], 84, 84), np.uint8),
            true_mask=None,
            reward=rng.uniform(0, 1, shape[1:]).astype(np.float32),
            discount=np.ones(shape[1:], np.float32),
            first=np.full(shape[1:], r == 0),
            last=None,
            success=None,
        )
        for r in range(rows)
    ]
    actions = rng.uniform(-1, 1, (*shape, action_dim)).astype(np.float32)
    for n in (1, 2):
        mesh = devices.seed_mesh(n, seeds)
        sharding = devices.seed_sharding(mesh)
        put = (lambda x: x) if mesh is None else (lambda x, s=sharding: jax.device_put(x, s))
        programs = build_programs(acfg, hp, c, mesh)
        agent = put(update.init_seeds(acfg, jax.random.split(jax.random.key(0), seeds)))
        buffer = put(replay.init(100, envs, (84, 84, 3), action_dim, leading=(seeds,)))
        for ts, action in zip(steps, actions):
            buffer = programs.add(buffer, put(ts), put(action))
        acted, agent = programs.act(
            agent, put(obs), jax.random.key(1), put(np.ones(shape[1:], bool))
        )
        agent, metrics = programs.learn(agent, buffer, jax.random.key(2))
        evaluated, cos, pred = programs.evaluate_step(agent.params, put(obs))
        out = {"act": acted, "evaluate": evaluated, "pred": pred, **cos, **metrics}
        for path, x in jax.tree_util.tree_leaves_with_path(agent.params):
            out[jax.tree_util.keystr(path)] = x
        where = sorted({len(x.sharding.device_set) for x in jax.tree.leaves(out)})
        np.savez(
            root / f"pallas_{n}.npz", where=where, **{k: np.asarray(v) for k, v in out.items()}
        )


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("sharding")
    _run_child("runs", root)
    return root, json.loads((root / "placements.json").read_text())


def _run_child(what: str, root: pathlib.Path) -> None:
    """This file as a script in a process with 4 CPU devices: `_child` ("runs") or
    `_pallas_child` ("pallas")."""
    flags = RUNS_FLAGS if what == "runs" else FLAGS
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu", MUJOCO_GL="egl")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    out = subprocess.run(
        [sys.executable, __file__, what, str(root)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-5000:]


@pytest.fixture(scope="module")
def pallas_programs(tmp_path_factory):
    root = tmp_path_factory.mktemp("pallas")
    _run_child("pallas", root)
    return [np.load(root / f"pallas_{n}.npz") for n in (1, 2)]


def test_pallas_stacks_run_split_over_devices(pallas_programs):
    """The Pallas conv stacks and filter gradients inside the sharded programs: act, add, learn
    (the fused mask loss included) and the evaluation step trace and run with the seeds split
    over 2 devices, their outputs stay split, and they give one device's numbers bit for bit."""
    one, split = pallas_programs
    assert list(one["where"]) == [1] and list(split["where"]) == [2]
    names = [k for k in one.files if k != "where"]
    assert sorted(names) == sorted(k for k in split.files if k != "where")
    assert {"act", "evaluate", "pred", "critic_loss", "mask_loss"} <= set(names)
    assert np.all(np.isfinite(one["mask_loss"])) and np.all(one["mask_loss"] > 0)
    for name in names:
        assert one[name].tobytes() == split[name].tobytes(), name


def test_a_split_run_is_the_same_run(runs):
    """Seeds split over 2 devices learn exactly what they learn on one: the checkpoint at CUT
    of the split run equals the one-device run's, bit for bit, after some updates."""
    from dear_jax.checkpoint import Checkpointer

    root, _ = runs
    one, split = (
        Checkpointer(root / w / "checkpoints", fingerprint={}).read_arrays(CUT)
        for w in ("whole", "from_split")
    )
    import jax

    flat = jax.tree_util.tree_flatten_with_path(one)[0]
    assert [p for p, _ in flat] == [p for p, _ in jax.tree_util.tree_flatten_with_path(split)[0]]
    for (path, x), y in zip(flat, jax.tree.leaves(split)):
        assert x.tobytes() == y.tobytes(), jax.tree_util.keystr(path)
    updates = Checkpointer(root / "whole" / "checkpoints", fingerprint={}).read_meta(CUT)[2]
    assert updates["counters"]["updates"] >= 5


@pytest.mark.parametrize("workdir", ["to_split", "from_split"])
def test_a_run_resumes_on_another_device_count(runs, workdir):
    """Stopped at CUT on 1 (2) devices and resumed on 2 (1), a run ends as the uninterrupted
    one-device run: checkpoint, replay files and logs."""
    from test_run import assert_same_run

    root, _ = runs
    # The eval log's cos(z_A, z_E) and |cos|, means of a few numbers in the evaluation program,
    # may round differently in their last bit on another split; the actions and returns do not.
    cosines = {"cos_agent_env", "abs_cos_agent_env"}
    assert_same_run(root / "whole", root / workdir, END, close_columns=cosines)
    summary = json.loads((root / workdir / "summary.json").read_text())
    assert summary["devices"] == (2 if workdir == "to_split" else 1)


def test_arrays_live_split_over_the_devices(runs):
    """Inside the runs (at each checkpoint, resumed ones included) every array with a seeds axis
    is split over the mesh, the loop's key is on every device, and one-device runs keep the
    default placement."""
    from jax.sharding import PartitionSpec as P

    _, placements = runs
    seeds, everywhere = str(P("seeds")), str(P())
    split = [p for p in placements["runs"] if p["devices"] > 1]
    assert {p["devices"] for p in split} == {2}
    assert len(split) == 2  # one of a run that resumed on 2 devices
    for p in split:
        n = p["devices"]
        for group in ("agent", "replay", "env", "timestep", "returns"):
            assert p[group] == [[seeds, n]], (group, p)
        assert p["key"] == [[everywhere, n]]
        assert p["physics_threads"] == n  # env.physics_threads=0: one per device
    single = [p for p in placements["runs"] if p["devices"] == 1]
    assert single and all(p["agent"] == [["None", 1]] for p in single)
    assert all(p["physics_threads"] == 1 for p in single)
    for name in ("state", "reward"):
        assert placements["mjx"][name] == [[seeds, 4]], name


def test_splits_that_cannot_work_are_refused_by_name(tmp_path):
    from dear_jax import devices, train

    with pytest.raises(ValueError, match=r"seeds=3 cannot be split evenly over devices=2 .* "):
        devices.num_devices(2, 3, available=4)
    with pytest.raises(ValueError, match=r"valid devices for 3 seeds: 1, 3;"):
        devices.num_devices("all", 3, available=4)
    with pytest.raises(ValueError, match=r"devices=8 but 4 .* exist here; valid: 1 to 4, or 'all'"):
        devices.num_devices(8, 8, available=4)
    with pytest.raises(ValueError, match=r"devices must be 'all' or an int >= 1, got 'two'"):
        devices.num_devices("two", 2, available=4)
    assert devices.num_devices("all", 8, available=4) == 4
    assert devices.num_devices(1, 3, available=1) == 1
    # The trainer refuses before anything is written (this process has one device).
    with pytest.raises(ValueError, match=r"devices=2 but 1 cpu device\(s\) exist here"):
        train.train(config(devices=2), tmp_path)
    assert not (tmp_path / "checkpoints").exists()


def test_devices_may_change_on_resume():
    from dear_jax import experiment

    assert "devices" in experiment.RESUMABLE_CHANGES
    assert experiment.fingerprint(config(devices="all")) == experiment.fingerprint(config())


if __name__ == "__main__":
    {"runs": _child, "pallas": _pallas_child}[sys.argv[1]](pathlib.Path(sys.argv[2]))
