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
CUT, END = 80, 120  # frames per seed: the first runs stop at CUT (updates start at 40)


def config(**overrides):
    """test_run's tiny config, evaluating and saving at CUT (where the first runs stop), updating
    from frame 40 on (5 updates per seed by CUT). The evaluations run on the training's devices
    with its programs (eval_device "train"), without videos: the runs start no evaluation
    process (its start, jax import included, cost ~5 s a run), and the split runs' evaluations
    run split too."""
    from test_run import tiny_config

    # "loop": each seed's program is the same whatever seeds share its device (docs/design.md).
    overrides = {
        "agent.seed_axis": "loop",
        "replay.seed_frames": 40,
        "eval_device": "train",
        "save_video": False,
        **overrides,
    }
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
    import shutil

    import jax
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from dear_jax import loop, train, update
    from dear_jax.devices import batch_split
    from envs import dmc
    from envs import physics as envs_physics
    from envs.physics import MjxPhysics

    assert len(jax.devices()) == 4, jax.devices()
    # Programs compiled once for the whole process, whose rounding no split is compared
    # against, at LLVM level 0 as in the test processes: the seeds' initial parameters (every
    # run's; 16 s to compile at the default level, 4 s at 0) and MJX's step below (14 s, 8 s).
    level_0 = {"xla_backend_optimization_level": 0}
    assert callable(loop._init_seeds)  # the program replaced here (a rename must show)
    loop._init_seeds = jax.jit(update.init_seeds, static_argnums=0, compiler_options=level_0)
    options = envs_physics._compiler_options
    envs_physics._compiler_options = lambda: {**(options() or {}), **level_0}
    placements = []
    save = loop.Loop.save

    def recording_save(run, wall_s):  # every checkpoint: after the start and after resuming
        devices = 1 if run.mesh is None else run.mesh.size
        per_seed = batch_split(run.mesh)
        placements.append({"devices": devices, "per_seed": per_seed, **_placements(run)})
        save(run, wall_s)

    loop.Loop.save = recording_save
    # Grouped by device count: the compiled programs of a process are those of its last mesh.
    train.train(config(total_frames=END), root / "whole")
    train.train(config(total_frames=CUT), root / "to_split")
    # A one-device run stopped at CUT, as to_split is now: into_per_seed resumes its copy below.
    shutil.copytree(root / "to_split", root / "into_per_seed")
    train.train(config(total_frames=CUT, devices=2), root / "from_split")
    train.train(config(total_frames=END, devices=2), root / "to_split")
    train.train(config(total_frames=END), root / "from_split")
    # Each seed's batch over 2 devices, then resumed on one; and the other way round.
    per_seed = {"devices": 2, "devices_per_seed": 2}
    train.train(config(total_frames=CUT, **per_seed), root / "per_seed")
    train.train(config(total_frames=END), root / "per_seed")
    train.train(config(total_frames=END, **per_seed), root / "into_per_seed")

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
    import jax.numpy as jnp

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
    # Both splits start from these parameters, made once (~4 s, traced op by op).
    init = jax.device_get(update.init_seeds(acfg, jax.random.split(jax.random.key(0), seeds)))
    for n in (1, 2):
        mesh = devices.seed_mesh(n, seeds)
        sharding = devices.seed_sharding(mesh)
        put = (lambda x: x) if mesh is None else (lambda x, s=sharding: jax.device_put(x, s))
        programs = build_programs(acfg, hp, c, mesh)
        agent = put(jax.tree.map(jnp.asarray, init))
        buffer = put(replay.init(100, envs, (84, 84, 3), action_dim, leading=(seeds,)))
        for ts, action in zip(steps, actions):
            buffer = programs.add(buffer, put(ts), put(action))
        acted, agent = programs.act(
            agent, put(obs), jax.random.key(1), put(np.ones(shape[1:], bool))
        )
        agent, metrics = programs.learn(agent, buffer, jax.random.key(2))
        evaluated, cos, pred = programs.evaluate_step(agent.params, put(obs))
        out = {"act": acted, "evaluate": evaluated, "pred": pred, "eval_cos": cos, **metrics}
        for path, x in jax.tree_util.tree_leaves_with_path(agent.params):
            out[jax.tree_util.keystr(path)] = x
        where = sorted({len(x.sharding.device_set) for x in jax.tree.leaves(out)})
        np.savez(
            root / f"pallas_{n}.npz", where=where, **{k: np.asarray(v) for k, v in out.items()}
        )


def _batch_child(root: pathlib.Path) -> None:
    """One learn call of 2 seeds on 4 devices, each seed's batch split over 2 of them
    (devices_per_seed=2: a 2 x 2 mesh, the update vmapped over the seeds of a device), and the
    same update on one device of the batch each seed's two devices drew, gathered; with nothing
    random inside the update (no shift, no action noise), the two must agree. Writes
    root/batch.npz: the split run's parameters and metrics (under "replicas", whether every
    array was in 2 blocks of seeds, each on 2 devices alike), and the gathered batch's."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from dear_jax import devices, experiment, replay, update
    from dear_jax.programs import build_programs

    seeds, envs, action_dim, rows = 2, 2, 6, 12
    no_noise = {"agent.std_init": 0.0, "agent.std_final": 0.0}
    c = config(
        seeds=seeds, devices=4, devices_per_seed=2, **{"agent.seed_axis": "vmap"}, **no_noise
    )
    experiment.validate(c)
    a = c.agent
    acfg = dataclasses.replace(experiment.agent_config(c, action_dim), augment_pad=0)
    hp = experiment.hparams(c)
    rng = np.random.default_rng(0)
    buffer = replay.init(100, envs, (84, 84, 3), action_dim, leading=(seeds,))
    add = jax.jit(jax.vmap(replay.add))
    for r in range(rows):
        buffer = add(
            buffer,
            rng.integers(0, 256, (seeds, envs, 84, 84, 3), np.uint8),
            rng.integers(0, 2, (seeds, envs, 84, 84), np.uint8),
            rng.uniform(-1, 1, (seeds, envs, action_dim)).astype(np.float32),
            rng.uniform(0, 1, (seeds, envs)).astype(np.float32),
            np.ones((seeds, envs), np.float32),
            np.full((seeds, envs), r == 0),
        )
    agent = update.init_seeds(acfg, jax.random.split(jax.random.key(0), seeds))
    key = jax.random.key(2)

    # The draws of the learn program (programs.build_programs), gathered into one batch.
    def draw(buffer, seed_key, device):
        k_sample, _ = jax.random.split(jax.random.fold_in(seed_key, device))
        return replay.sample(
            buffer, k_sample, a.batch_size // 2, nstep=a.nstep, gamma=a.discount, frame_stack=3
        )

    seed_keys = jax.random.split(key, seeds)
    halves = [jax.vmap(draw, (0, 0, None))(buffer, seed_keys, d) for d in (0, 1)]
    gather = lambda x, y: jnp.concatenate([x, y], axis=1)  # noqa: E731
    one = jax.jit(jax.vmap(lambda s, b, k, h: update.update(s, b, k, h, cfg=acfg)))
    whole = one(agent, jax.tree.map(gather, *halves), seed_keys, hp)
    # Had both devices drawn the same half: what the split run must not equal.
    repeated = one(agent, jax.tree.map(gather, halves[0], halves[0]), seed_keys, hp)

    # learn donates the agent, whose device-0 buffers the split's may share: it runs last.
    mesh = devices.seed_mesh(c.devices, seeds, c.devices_per_seed)
    assert dict(mesh.shape) == {"seeds": 2, "batch": 2}, mesh.shape
    put = lambda x: jax.device_put(x, devices.seed_sharding(mesh))  # noqa: E731
    split_agent, split_metrics = build_programs(acfg, hp, c, mesh).learn(
        put(agent), put(buffer), key
    )

    def two_blocks_twice(x) -> bool:
        blocks = {}
        for shard in x.addressable_shards:
            index = tuple((i.start, i.stop) for i in shard.index)
            blocks.setdefault(index, []).append(np.asarray(shard.data).tobytes())
        return len(blocks) == 2 and all(len(b) == 2 and b[0] == b[1] for b in blocks.values())

    replicas = all(map(two_blocks_twice, jax.tree.leaves((split_agent, split_metrics))))

    out = {"replicas": replicas}
    for name, (state, metrics) in [
        ("split", (split_agent, split_metrics)),
        ("whole", whole),
        ("repeated", repeated),
    ]:
        # The optimisers' first moments are the (averaged) gradients themselves: Adam's first
        # step, about lr * sign(gradient), would hide a wrong mean from the parameters alone.
        moments = (state.opt_state, state.actor_opt_state)
        for path, x in jax.tree_util.tree_leaves_with_path((state.params, metrics, moments)):
            out[name + jax.tree_util.keystr(path)] = np.asarray(x)
    np.savez(root / "batch.npz", **out)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("sharding")
    _run_child("runs", root)
    return root, json.loads((root / "placements.json").read_text())


def _run_child(what: str, root: pathlib.Path) -> None:
    """This file as a script in a process with 4 CPU devices: `_child` ("runs"), `_pallas_child`
    ("pallas") or `_batch_child` ("batch")."""
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


def test_a_lanes_batch_split_over_devices_takes_the_whole_batchs_step(tmp_path):
    """devices_per_seed=2, 2 seeds on 4 devices: each device draws its own half of its seed's
    batch, and the averaged gradients give both devices the step that one device takes on the
    two halves together (float32 sums in another order: close, not equal); each seed lives on
    its 2 devices, whose copies stay bit for bit equal."""
    _run_child("batch", tmp_path)
    out = np.load(tmp_path / "batch.npz")
    assert bool(out["replicas"])
    names = [k.removeprefix("split") for k in out.files if k.startswith("split")]
    assert len(names) > 20 and "[1]['mask_loss']" in names
    for name in names:
        np.testing.assert_allclose(
            out["split" + name], out["whole" + name], rtol=2e-5, atol=2e-6, err_msg=name
        )
    # Each device drew its own half: one half taken twice gives other losses and gradients.
    moments = [n for n in names if n.startswith("[2]") and "mu" in n and "critic" in n]
    assert moments, names
    for name in ("[1]['critic_loss']", *moments):
        assert not np.allclose(out["split" + name], out["repeated" + name], rtol=1e-3), name


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
    split = [p for p in placements["runs"] if p["devices"] > 1 and p["per_seed"] == 1]
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


def test_a_run_with_each_seeds_batch_over_two_devices(runs):
    """devices_per_seed=2: both seeds live whole on both devices (replicated over "batch"), the
    run trains, resumes on one device to the end, and a one-device run resumes onto 2 devices
    per seed to the end, saying so in its summary."""
    from jax.sharding import PartitionSpec as P

    from dear_jax.checkpoint import Checkpointer
    from dear_jax.logger import read_csv

    root, placements = runs
    split = [p for p in placements["runs"] if p["per_seed"] == 2]
    assert len(split) == 2  # the per_seed run's first checkpoint, into_per_seed's after resuming
    # The mesh is 1 x 2 ("seeds" x "batch"): over a seeds axis of one device, P("seeds") and
    # P() (XLA's name for some outputs) are the same layout, whole on both devices.
    whole = {str(P("seeds")), str(P())}
    for p in split:
        for group in ("agent", "replay", "env", "timestep", "returns"):
            assert {spec for spec, _ in p[group]} <= whole, (group, p)
            assert {n for _, n in p[group]} == {2}, (group, p)
        assert p["devices"] == 2
    saved = Checkpointer(root / "per_seed" / "checkpoints", fingerprint={})
    counters = saved.read_meta(CUT)[2]["counters"]
    assert counters["updates"] >= 5 and counters["frame"] == CUT
    arrays = saved.read_arrays(CUT)
    import jax

    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(arrays) if x.dtype.kind == "f")
    for workdir, devices, per_seed in (("per_seed", 1, 1), ("into_per_seed", 2, 2)):
        summary = json.loads((root / workdir / "summary.json").read_text())
        assert (summary["devices"], summary["devices_per_seed"]) == (devices, per_seed)
        assert summary["frames_per_seed"] == END
        for seed in ("seed_0", "seed_1"):
            frames = read_csv(root / workdir / seed / "eval.csv")["frame"].tolist()
            assert frames[-1] == END, (workdir, frames)


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
    with pytest.raises(
        ValueError,
        match=r"devices=3 \(3 devices\) cannot be split into groups of devices_per_seed=2",
    ):
        devices.num_devices(3, 1, available=4, per_seed=2)
    with pytest.raises(
        ValueError,
        match=r"seeds=3 cannot be split evenly over devices=4 \(4 devices in groups of devices_per_seed=2\); valid devices for 3 seeds: 2;",
    ):
        devices.num_devices(4, 3, available=4, per_seed=2)
    with pytest.raises(ValueError, match=r"devices_per_seed must be an int >= 1, got 0"):
        devices.num_devices(2, 2, available=4, per_seed=0)
    assert devices.num_devices(4, 1, available=4, per_seed=4) == 4
    with pytest.raises(
        ValueError, match=r"agent.batch_size=5 cannot be split evenly over devices_per_seed=2"
    ):
        train.train(config(devices=2, devices_per_seed=2, **{"agent.batch_size": 5}), tmp_path)
    assert devices.num_devices(1, 3, available=1) == 1
    # The trainer refuses before anything is written (this process has one device).
    with pytest.raises(ValueError, match=r"devices=2 but 1 cpu device\(s\) exist here"):
        train.train(config(devices=2), tmp_path)
    assert not (tmp_path / "checkpoints").exists()


def test_devices_may_change_on_resume():
    from dear_jax import experiment

    assert {"devices", "devices_per_seed"} <= set(experiment.RESUMABLE_CHANGES)
    assert experiment.fingerprint(config(devices="all")) == experiment.fingerprint(config())
    split = config(devices=2, devices_per_seed=2)
    assert experiment.fingerprint(split) == experiment.fingerprint(config())


if __name__ == "__main__":
    {"runs": _child, "pallas": _pallas_child, "batch": _batch_child}[sys.argv[1]](
        pathlib.Path(sys.argv[2])
    )
