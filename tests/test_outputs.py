"""Run outputs: per-seed CSV + TensorBoard logs, orbax checkpoints, eval videos, learning curves."""

import json
import os
import pathlib
import struct
import subprocess
import sys
import textwrap

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ml_collections import ConfigDict
from tensorboardX.proto import event_pb2

from dear_jax import claims, lanes, lock, plot, report, update
from dear_jax.checkpoint import Checkpointer, IncompatibleCheckpointError
from dear_jax.logger import RunLogger, format_table, read_csv
from dear_jax.video import SEPARATOR_RGB, side_by_side, write_video

REPO = pathlib.Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- logger


def test_csv_rows_per_seed_and_scalar_broadcast(tmp_path):
    with RunLogger(tmp_path, 3, tensorboard=False) as log:
        log.write("train", 100, {"loss": np.array([0.5, 1.5, 2.5]), "episode": 4, "fps": 12.25})
        log.write("train", 200, {"loss": np.array([0.25, 1.25, 2.25]), "episode": 8, "fps": 3.0})
    for seed in range(3):
        cols = read_csv(tmp_path / f"seed_{seed}" / "train.csv")
        assert list(cols) == ["frame", "loss", "episode", "fps"]
        np.testing.assert_array_equal(cols["frame"], [100, 200])
        np.testing.assert_array_equal(cols["loss"], [0.5 + seed, 0.25 + seed])
        np.testing.assert_array_equal(cols["episode"], [4, 8])
        np.testing.assert_array_equal(cols["fps"], [12.25, 3.0])
    assert not (tmp_path / "seed_3").exists()


def test_csv_keeps_full_float_precision_and_nan(tmp_path):
    value = np.float32(0.1)  # not exactly representable: a short format would change it
    with RunLogger(tmp_path, 2, tensorboard=False) as log:
        log.write("eval", 10, {"x": np.array([value, np.nan], np.float32)})
    assert read_csv(tmp_path / "seed_0" / "eval.csv")["x"][0] == float(value)
    assert np.isnan(read_csv(tmp_path / "seed_1" / "eval.csv")["x"][0])


def test_csv_header_is_the_union_of_metrics(tmp_path):
    with RunLogger(tmp_path, 2, tensorboard=False) as log:
        log.write("eval", 10, {"episode_return": np.array([1.0, 2.0])})
        log.write("eval", 20, {"episode_return": np.array([3.0, 4.0]), "success": 1.0})
        log.write("eval", 30, {"success": np.array([0.0, 0.5])})
    path = tmp_path / "seed_1" / "eval.csv"
    assert path.read_text().splitlines()[0] == "frame,episode_return,success"
    cols = read_csv(path)
    np.testing.assert_array_equal(cols["frame"], [10, 20, 30])
    np.testing.assert_array_equal(cols["episode_return"], [2.0, 4.0, np.nan])
    np.testing.assert_array_equal(cols["success"], [np.nan, 1.0, 0.5])
    assert not list(tmp_path.rglob("*.tmp"))


def test_a_detached_runs_log_line_says_how_far_it_is_and_how_long_is_left():
    """The console's line per log row off a terminal: 250k of 1M frames per seed at 1,250 frames/s
    per seed leaves 750,000 / 1,250 = 600 s; no rate yet, no estimate."""
    from dear_jax.progress import _left

    assert _left(250_000, 1_000_000, 1250.0) == "25% of 1,000,000, ~10 min left"
    assert _left(1_170, 1_200, 40.0) == "98% of 1,200, <1 min left"
    assert _left(0, 1_200, float("nan")) == "0% of 1,200"


def test_train_rows_average_the_returns_of_episodes_ended_at_different_steps(tmp_path):
    """Kitchen envs end on success, each at its own step: the loop's device sums (programs.
    accumulate), kept in the carry until a row reads them, give each seed's mean return; pending
    sums survive a checkpoint's extra."""
    from types import SimpleNamespace

    from dear_jax.carry import Carry
    from dear_jax.checkpoint import _decode_arrays, _jsonable
    from dear_jax.devices import Hosts
    from dear_jax.programs import accumulate
    from dear_jax.progress import Progress, TrainLog

    hosts = Hosts(None, 2)

    def carry():
        return Carry(hosts, agent=None, buffer=None, key=None, state=None, ts=None,
                     returns=jnp.zeros((2, 3)), seed_frames=0, log_every=1)  # fmt: skip

    c = carry()
    # 2 seeds x 3 envs. Seed 0: env 0 ends at step 2 (1 + 2), env 1 at step 3 (3 + 0 + 4), env 2
    # never; seed 1: env 2 ends at step 3 (6 + 6 + 6).
    rewards = [[[1, 3, 8], [5, 5, 6]], [[2, 0, 8], [5, 5, 6]], [[9, 4, 8], [5, 5, 6]]]
    lasts = [[[0, 0, 0], [0, 0, 0]], [[1, 0, 0], [0, 0, 0]], [[0, 1, 0], [0, 0, 1]]]
    firsts = [[[0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 0]], [[1, 0, 0], [0, 0, 0]]]
    for reward, last, first in zip(rewards, lasts, firsts, strict=True):
        ts = SimpleNamespace(reward=jnp.array(reward, jnp.float32), last=jnp.array(last, bool),
                             first=jnp.array(first, bool))  # fmt: skip
        c.returns, ended_returns = accumulate(c.returns, ts)
        c.add_ended(ended_returns, np.array(last, bool))
    expected = [[[3.0, 0.0], [1, 0]], [[7.0, 18.0], [1, 1]]]
    np.testing.assert_array_equal(c.ended_episodes(), expected)
    # A checkpoint's extra (json) and back.
    extra = c.extra(env_rng={}, eval_env_rng={}, replay_on_disk=False)
    resumed = carry()
    resumed.load_host_values(_decode_arrays(_jsonable(extra, "extra")), 10)
    np.testing.assert_array_equal(resumed.ended_episodes(), expected)
    assert resumed.episodes_pending
    c.counters["frame"], c.counters["iteration"], c.episodes_pending = 3, 3, True
    with RunLogger(tmp_path, 2, tensorboard=False) as log:
        TrainLog(
            log, Progress(False, 10, 0), hosts, 2, 1, 0.0, iteration=0, updates=0, host_seconds=dict
        ).write_if_due(c)
    returns = [read_csv(tmp_path / f"seed_{s}" / "train.csv")["episode_return"] for s in (0, 1)]
    np.testing.assert_array_equal(returns, [[5.0], [18.0]])  # (3 + 7) / 2; 18 / 1
    assert c.episode_returns == []


def test_stage_means_weigh_rows_by_their_iterations():
    """The summary's ms per iteration: rows of more iterations weigh more; untimed rows (NaN:
    a process's compilations) and columns other than `*_ms` are left out; a log without
    `iterations` (older runs) weighs its rows equally."""
    from dear_jax.summary import stage_means

    log = {
        "frame": np.array([10, 20, 30, 40]),
        "iteration_ms": np.array([99.0, np.nan, 10.0, 20.0]),
        "env_draw_ms": np.array([99.0, np.nan, 4.0, 8.0]),
        "iterations": np.array([np.nan, 50.0, 1.0, 3.0]),  # row 0: written by older code
        "fps": np.array([1.0, 1.0, 2.0, 3.0]),
    }
    assert stage_means(log) == {"iteration_ms": 17.5, "env_draw_ms": 7.0}
    assert stage_means(log, slice(0, 3)) == {"iteration_ms": 10.0, "env_draw_ms": 4.0}
    del log["iterations"]
    assert stage_means(log) == {"iteration_ms": 43.0, "env_draw_ms": 37.0}
    assert stage_means({"frame": np.array([1]), "iteration_ms": np.array([np.nan])}) == {}


def test_write_rejects_bad_kind_and_shape(tmp_path):
    with RunLogger(tmp_path, 2, tensorboard=False) as log:
        with pytest.raises(ValueError, match="valid: train, eval"):
            log.write("test", 0, {"a": 1.0})
        with pytest.raises(ValueError, match=r"'a' has shape \(3,\).*\(2,\)"):
            log.write("train", 0, {"a": np.zeros(3)})


def test_resume_drops_rows_after_the_checkpoint_frame(tmp_path, caplog):
    with RunLogger(tmp_path, 2, tensorboard=False) as log:
        for frame in (10, 20, 30, 40):
            log.write("train", frame, {"r": np.array([frame, -frame])})
        log.write("eval", 20, {"r": 1.0})
        log.write("eval", 40, {"r": 2.0})
    with RunLogger(tmp_path, 2, tensorboard=False, resume_frame=20) as log:
        np.testing.assert_array_equal(read_csv(tmp_path / "seed_1/train.csv")["r"], [-10, -20])
        np.testing.assert_array_equal(read_csv(tmp_path / "seed_0/eval.csv")["frame"], [20])
        log.write("train", 30, {"r": np.array([300, -300])})
    cols = read_csv(tmp_path / "seed_0" / "train.csv")
    np.testing.assert_array_equal(cols["frame"], [10, 20, 30])
    np.testing.assert_array_equal(cols["r"], [10, 20, 300])
    assert (tmp_path / "seed_0" / "train.csv").read_text().count("frame") == 1
    # A fresh run in the same workdir starts new files, and says once which logs it replaces.
    with caplog.at_level("WARNING", logger="dear_jax.logger"):
        with RunLogger(tmp_path, 2, tensorboard=False) as log:
            log.write("train", 5, {"r": 1.0})
    (said,) = [
        r.getMessage() for r in caplog.records if "no checkpoint to resume" in r.getMessage()
    ]
    assert "training starts at frame 0" in said and "train.csv, to frame 30) are replaced" in said
    np.testing.assert_array_equal(read_csv(tmp_path / "seed_0/train.csv")["frame"], [5])
    assert not (tmp_path / "seed_0" / "eval.csv").exists()


def _tfrecords(path):
    """Records of a TFRecord file: u64 length, u32 crc, payload, u32 crc."""
    data, pos = path.read_bytes(), 0
    while pos < len(data):
        (length,) = struct.unpack("<Q", data[pos : pos + 8])
        yield data[pos + 12 : pos + 12 + length]
        pos += 12 + length + 4


def _scalars(tb_dir):
    out = {}
    for path in sorted(tb_dir.glob("events.out.tfevents.*")):
        for record in _tfrecords(path):
            event = event_pb2.Event.FromString(record)
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out


def test_tensorboard_scalars_read_back(tmp_path):
    log = RunLogger(tmp_path, 2)
    log.write("train", 100, {"loss": np.array([0.5, 1.5]), "fps": 7.0})
    log.write("eval", 200, {"episode_return": np.array([10.0, 20.0])})
    # Flushed after each write: readable before close (a killed run keeps its logs).
    seed1 = _scalars(tmp_path / "seed_1" / "tb")
    assert seed1 == {
        "train/loss": [(100, 1.5)],
        "train/fps": [(100, 7.0)],
        "eval/episode_return": [(200, 20.0)],
    }
    log.close()
    assert _scalars(tmp_path / "seed_0" / "tb")["train/loss"] == [(100, 0.5)]


def _session_starts(tb_dir):
    return [
        event_pb2.Event.FromString(r).step
        for path in sorted(tb_dir.glob("events.out.tfevents.*"))
        for r in _tfrecords(path)
        if event_pb2.Event.FromString(r).HasField("session_log")
    ]


def test_tensorboard_resume_purges_and_fresh_run_restarts(tmp_path):
    with RunLogger(tmp_path, 1) as log:
        log.write("train", 100, {"loss": 1.0})
        log.write("train", 200, {"loss": 2.0})
    with RunLogger(tmp_path, 1, resume_frame=100) as log:
        log.write("train", 200, {"loss": 3.0})
    tb = tmp_path / "seed_0" / "tb"
    # TensorBoard drops the old run's events from step 101 on when it meets this marker.
    assert _session_starts(tb) == [101]
    assert _scalars(tb)["train/loss"] == [(100, 1.0), (200, 2.0), (200, 3.0)]
    with RunLogger(tmp_path, 1) as log:
        log.write("train", 50, {"loss": 5.0})
    assert _scalars(tb) == {"train/loss": [(50, 5.0)]} and _session_starts(tb) == []


def _visible(tb_dir):
    """The scalars TensorBoard shows: a START marker at step p hides the earlier events at
    steps >= p (its purge of a resumed run's)."""
    out = {}
    for path in sorted(tb_dir.glob("events.out.tfevents.*")):
        for record in _tfrecords(path):
            event = event_pb2.Event.FromString(record)
            if event.HasField("session_log"):
                out = {t: [(s, v) for s, v in pts if s < event.step] for t, pts in out.items()}
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out


def test_tensorboard_shows_a_redone_evaluation_once(tmp_path):
    """A run resumed from a checkpoint that holds an evaluation as due redoes it: TensorBoard
    shows the new point alone at that frame, and the training row kept there once."""
    with RunLogger(tmp_path, 1) as log:
        log.write("train", 100, {"loss": 1.0})
        log.write("eval", 100, {"episode_return": 7.0})
        log.write("train", 200, {"loss": 2.0})
    with RunLogger(tmp_path, 1, resume_frame=100, redo=("eval",)) as log:
        log.write("eval", 100, {"episode_return": 8.0})
        log.write("train", 200, {"loss": 3.0})
    assert _visible(tmp_path / "seed_0" / "tb") == {
        "train/loss": [(100, 1.0), (200, 3.0)],
        "eval/episode_return": [(100, 8.0)],
    }
    assert read_csv(tmp_path / "seed_0" / "eval.csv")["episode_return"].tolist() == [8.0]


def test_format_table():
    table = format_table(["seed", "return", "note"], [[0, "812.5", "ok"], [11, "7.25", ""]])
    assert table == (
        "| seed | return | note |\n"
        "|-----:|-------:|------|\n"
        "|    0 |  812.5 | ok   |\n"
        "|   11 |   7.25 |      |"
    )
    with pytest.raises(ValueError, match="row 0 has 1 cells; the header has 2"):
        format_table(["a", "b"], [[1]])


# ---------------------------------------------------------------- checkpoints

FINGERPRINT = {"env.task": "walker-walk", "agent.method": "dear", "seeds": 2, "widths": (64, 32)}


@pytest.fixture(scope="module")
def agent_state():
    """A small AgentState with a leading seed axis of 2 and different values per seed."""
    cfg = update.AgentConfig(action_dim=2, latent_dim=64, hidden_dim=32, feature_dim=8)
    one = jax.jit(update.init, static_argnums=0)(cfg, jax.random.key(0))  # eager: op by op
    return jax.tree.map(lambda x: jnp.stack([x, x * 3 + 1]), one)


def _state(agent, i=0):
    return {
        "agent": jax.tree.map(lambda x: x + i, agent),
        "key": jax.random.key_data(jax.random.split(jax.random.key(7 + i), 2)),
        "typed_key": jax.random.key(11 + i),
        "counters": {"updates": np.int32(5 + i), "frame": jnp.int32(1000 * i)},
    }


def _assert_identical(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def test_checkpoint_round_trip_is_bit_identical(tmp_path, agent_state):
    state = _state(agent_state, 1)
    # Values that survive only if nothing is cast or rounded on the way.
    state["agent"] = state["agent"].replace(steps=jnp.array([2**31 - 1, -7], jnp.int32))
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        assert ckpt.latest_step() is None
        ckpt.save(1000, state, extra={"frame": 1000, "wall_s": 12.5, "episode": [1, 2]})
    template = _state(agent_state, 0)
    with Checkpointer(tmp_path / "ck", fingerprint=dict(FINGERPRINT)) as ckpt:
        assert ckpt.latest_step() == 1000
        step, restored, extra = ckpt.restore(template)
    assert step == 1000 and extra == {"frame": 1000, "wall_s": 12.5, "episode": [1, 2]}
    assert isinstance(restored["agent"], update.AgentState)
    _assert_identical(restored, state)
    for leaf in jax.tree.leaves(restored):
        assert isinstance(leaf, jax.Array) and leaf.devices() == {jax.devices()[0]}
    assert jax.random.key_impl(restored["typed_key"]) == jax.random.key_impl(state["typed_key"])
    # The restored key draws the same numbers as the saved one.
    np.testing.assert_array_equal(
        jax.random.uniform(restored["typed_key"], (3,)),
        jax.random.uniform(state["typed_key"], (3,)),
    )


def test_checkpoint_keeps_host_arrays_and_zero_size_leaves(tmp_path):
    """numpy arrays in `extra` (host RNG states, CPU physics) come back bit for bit, float64
    included; a zero-size leaf (not stored: orbax refuses it) comes back as the template's; a
    float64 numpy leaf of the state comes back as float32, as jax.numpy would make it."""
    rng_state = np.array([0.1, np.pi, -1e-300], np.float64)
    counts = np.array([[2**62, -1]], np.int64)
    state = {"w": jnp.arange(3.0), "empty": jnp.zeros((0, 3)), "host": np.array([0.1, 2.5])}
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(5, state, extra={"rng": rng_state, "physics": {"counts": counts}})
    template = {"w": jnp.zeros(3), "empty": jnp.zeros((0, 3)), "host": np.zeros(2)}
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        _, restored, extra = ckpt.restore(template)
    for got, want in ((extra["rng"], rng_state), (extra["physics"]["counts"], counts)):
        assert got.dtype == want.dtype and got.shape == want.shape
        assert got.tobytes() == want.tobytes()
    np.testing.assert_array_equal(restored["w"], [0.0, 1.0, 2.0])
    assert restored["empty"].shape == (0, 3)
    assert restored["host"].dtype == jnp.float32
    np.testing.assert_array_equal(restored["host"], np.float32([0.1, 2.5]))


@pytest.mark.parametrize("kept", [16, -256])  # its metadata lost, or only its arrays' last bytes
def test_a_damaged_checkpoint_is_named_with_the_one_before(tmp_path, kept):
    """The latest checkpoint's files cut short after it was written: restoring it says which
    checkpoint cannot be read and which one comes before it, and that one restores."""
    from dear_jax.checkpoint import UnreadableCheckpointError

    state = {"w": jnp.arange(4096.0)}
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(10, state)
        ckpt.save(20, {"w": state["w"] + 1})
    data = [p for p in (tmp_path / "ck" / "20").rglob("*") if p.is_file() and p.parent.name == "d"]
    assert data  # ocdbt's data files
    for path in data:
        path.write_bytes(path.read_bytes()[:kept])
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        with pytest.raises(UnreadableCheckpointError) as error:
            ckpt.restore({"w": jnp.zeros(4096)})
        step, restored, _ = ckpt.restore({"w": jnp.zeros(4096)}, step=10)
    message = str(error.value)
    assert f"checkpoint 20 in {tmp_path / 'ck'} cannot be read" in message
    assert f"Move {tmp_path / 'ck' / '20'} out of" in message and "from checkpoint 10" in message
    assert step == 10
    np.testing.assert_array_equal(restored["w"], state["w"])


@pytest.mark.parametrize("damage", ["cut", "emptied"])
def test_a_checkpoint_with_damaged_metadata_is_named_with_the_one_before(tmp_path, damage):
    """The latest checkpoint's metadata (its JSON) cut short or emptied: reading it says which
    checkpoint cannot be read, why, and which one comes before it, and that one reads."""
    from dear_jax.checkpoint import UnreadableCheckpointError

    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(10, {"w": jnp.arange(4.0)}, extra={"frame": 10})
        ckpt.save(20, {"w": jnp.arange(4.0) + 1}, extra={"frame": 20})
    meta = [p for p in (tmp_path / "ck" / "20" / "meta").rglob("*") if p.is_file()]
    assert meta
    for path in meta:
        path.write_text(path.read_text()[:20] if damage == "cut" else "")
    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        with pytest.raises(UnreadableCheckpointError) as error:
            ckpt.read_meta()
        step, _, extra = ckpt.read_meta(10)
    message = str(error.value)
    assert f"checkpoint 20 in {tmp_path / 'ck'} cannot be read" in message
    assert "its metadata: JSONDecodeError" in message and "from checkpoint 10" in message
    assert (step, extra) == (10, {"frame": 10})


def test_a_checkpoint_with_damaged_metadata_does_not_stop_the_next_save(tmp_path, caplog):
    """The replay files a save keeps are those of the kept checkpoints: one saved without the
    replay on disk or after the given row count needs none. While one's metadata cannot be read,
    which files it needs is unknown: none is deleted, a warning names it, and the save goes on."""
    from dear_jax.loop import replay_rows_kept

    def extra(rows, on_disk=True):
        return {"replay_on_disk": on_disk, "counters": {"rows": rows}}

    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT, keep=5) as ckpt:
        for step, meta in [(10, extra(100, False)), (20, extra(200)), (30, extra(300))]:
            ckpt.save(step, {"w": jnp.arange(4.0)}, extra=meta)
        ckpt.save(40, {"w": jnp.arange(4.0)}, extra=extra(400))
        assert replay_rows_kept(ckpt, 400) == {200, 300, 400}
        assert replay_rows_kept(ckpt, 350) == {200, 300}
        for path in (tmp_path / "ck" / "20" / "meta").rglob("*"):
            if path.is_file():
                path.write_text("")
        with caplog.at_level("WARNING", logger="dear_jax"):
            assert replay_rows_kept(ckpt, 400) is None
    assert f"checkpoint 20 in {tmp_path / 'ck'} cannot be read" in caplog.text
    assert "No replay file is deleted while it is kept" in caplog.text


def test_a_process_damaged_host_state_is_named_as_unreadable(tmp_path):
    """With several processes each keeps its host state in a file of its own beside the
    checkpoint: that file cut short reads as an unreadable checkpoint, named with its path."""
    from dear_jax.checkpoint import UnreadableCheckpointError

    with Checkpointer(tmp_path / "ck", fingerprint=FINGERPRINT) as ckpt:
        ckpt._own = str(tmp_path / "ck_process_1")  # as process 1 of several would
        os.makedirs(ckpt._own)
        ckpt.save(10, {"w": jnp.arange(4.0)}, extra={"frame": 10})
        ckpt.save(20, {"w": jnp.arange(4.0)}, extra={"frame": 20})
        own = tmp_path / "ck_process_1" / "20.json"
        own.write_text(own.read_text()[:5])
        assert ckpt.read_meta(10)[2] == {"frame": 10}
        with pytest.raises(UnreadableCheckpointError) as error:
            ckpt.read_meta(20)
    assert f"checkpoint 20 in {tmp_path / 'ck'} cannot be read" in str(error.value)
    assert f"{own}: JSONDecodeError" in str(error.value)


def test_keep_last_k_and_same_step(tmp_path, agent_state):
    with Checkpointer(tmp_path, fingerprint=FINGERPRINT, keep=2) as ckpt:
        for step in (10, 20, 30):
            assert ckpt.save(step, _state(agent_state, step), extra={"frame": step})
        assert ckpt.all_steps() == [20, 30]
        assert not ckpt.save(30, _state(agent_state, 99))  # already saved: left as it was
        _, restored, extra = ckpt.restore(_state(agent_state), step=20)
        assert extra == {"frame": 20}
        _assert_identical(restored, _state(agent_state, 20))
        _, restored, _ = ckpt.restore(_state(agent_state))
        _assert_identical(restored, _state(agent_state, 30))
        with pytest.raises(FileNotFoundError, match=r"available steps: \[20, 30\]"):
            ckpt.restore(_state(agent_state), step=10)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.isdigit()) == ["20", "30"]


def test_asynchronous_save(tmp_path, agent_state):
    with Checkpointer(tmp_path, fingerprint=FINGERPRINT, asynchronous=True) as ckpt:
        ckpt.save(1, _state(agent_state, 1))
        ckpt.wait()
        assert ckpt.latest_step() == 1
        _, restored, _ = ckpt.restore(_state(agent_state))
    _assert_identical(restored, _state(agent_state, 1))


def test_fingerprint_mismatch_names_every_key(tmp_path):
    state = {"w": jnp.arange(3.0)}
    with Checkpointer(tmp_path, fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(1, state)
    now = dict(FINGERPRINT, seeds=5, **{"agent.method": "drqv2", "replay.capacity": 100})
    with Checkpointer(tmp_path, fingerprint=now) as ckpt:
        with pytest.raises(IncompatibleCheckpointError) as err:
            ckpt.restore(state)
    msg = str(err.value)
    assert "seeds: saved=2, now=5" in msg
    assert "agent.method: saved='dear', now='drqv2'" in msg
    assert "replay.capacity: saved='<absent>', now=100" in msg
    assert "env.task" not in msg and "widths" not in msg  # equal keys are not listed
    assert "new --workdir" in msg


def test_a_field_added_later_resumes_at_its_old_behaviour(tmp_path):
    """A checkpoint written before a field existed resumes when the config gives the field the
    value that does what the code did before it (`added_fields`), and only then."""
    state = {"w": jnp.arange(3.0)}
    with Checkpointer(tmp_path, fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(1, state)
    added = {"env.render.mesh_faces": 0}
    now = dict(FINGERPRINT, **{"env.render.mesh_faces": 0})
    with Checkpointer(tmp_path, fingerprint=now, added_fields=added) as ckpt:
        step, restored, _ = ckpt.restore(state)
    assert step == 1
    np.testing.assert_array_equal(restored["w"], state["w"])
    changed = dict(FINGERPRINT, **{"env.render.mesh_faces": 4000})
    with Checkpointer(tmp_path, fingerprint=changed, added_fields=added) as ckpt:
        with pytest.raises(
            IncompatibleCheckpointError,
            match=r"mesh_faces: saved='<absent>', now=4000 \(a field newer than the checkpoint: "
            r"0 resumes it\)",
        ):
            ckpt.restore(state)
    with Checkpointer(tmp_path, fingerprint=now) as ckpt:  # not declared as added: refused
        with pytest.raises(
            IncompatibleCheckpointError, match="mesh_faces: saved='<absent>', now=0"
        ):
            ckpt.restore(state)


def test_template_mismatch_is_a_clear_error(tmp_path):
    with Checkpointer(tmp_path, fingerprint=FINGERPRINT) as ckpt:
        ckpt.save(1, {"w": jnp.arange(3.0), "n": jnp.int32(1)})
        with pytest.raises(ValueError, match=r"w: saved float32\[3\], template float32\[4\]"):
            ckpt.restore({"w": jnp.arange(4.0), "n": jnp.int32(1)})
        with pytest.raises(ValueError, match=r"n: saved int32\[\], template float32\[\]"):
            ckpt.restore({"w": jnp.arange(3.0), "n": jnp.float32(1)})
        with pytest.raises(ValueError, match="m: not in the checkpoint") as err:
            ckpt.restore({"w": jnp.arange(3.0), "m": jnp.int32(1)})
        assert "n: not in the template" in str(err.value)


CRASH_SCRIPT = textwrap.dedent(
    """
    import os, sys
    import jax.numpy as jnp
    from orbax.checkpoint._src.path import atomicity
    from dear_jax.checkpoint import Checkpointer

    ckpt = Checkpointer(sys.argv[1], fingerprint={"a": 1})
    ckpt.save(1, {"w": jnp.arange(1000.0), "n": jnp.int32(1)}, extra={"frame": 1})

    async def die(self):
        os._exit(17)  # killed after the arrays are written, before the step is committed

    atomicity.AtomicRenameTemporaryPath.finalize = die
    ckpt.save(2, {"w": jnp.zeros(1000), "n": jnp.int32(2)}, extra={"frame": 2})
    """
)


def test_crash_mid_save_keeps_previous_checkpoint(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", CRASH_SCRIPT, str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 17, proc.stderr[-2000:]
    leftovers = [p.name for p in tmp_path.iterdir() if "tmp" in p.name]
    assert leftovers and all(name.startswith("2.") for name in leftovers)  # the half-written step
    with Checkpointer(tmp_path, fingerprint={"a": 1}) as ckpt:
        assert ckpt.latest_step() == 1
        step, restored, extra = ckpt.restore({"w": jnp.zeros(1000), "n": jnp.int32(0)})
        assert step == 1 and extra == {"frame": 1} and int(restored["n"]) == 1
        np.testing.assert_array_equal(restored["w"], np.arange(1000.0))
        assert not [p for p in tmp_path.iterdir() if "tmp" in p.name]  # cleaned on open
        assert ckpt.save(2, {"w": jnp.ones(1000), "n": jnp.int32(2)})
        assert ckpt.all_steps() == [1, 2]


# ---------------------------------------------------------------- videos


def _clip(t=5, h=12, w=16, seed=0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
    true_mask = rng.integers(0, 2, (t, h, w)).astype(np.uint8)
    pred = rng.random((t, h, w)).astype(np.float32)
    return rgb, true_mask, pred


def test_side_by_side_layout():
    rgb, true_mask, pred = _clip()
    out = side_by_side(rgb, true_mask, pred, upscale=2, separator=3)
    assert out.dtype == np.uint8 and out.shape == (5, 24, 3 * 32 + 2 * 3, 3)
    up = lambda x: x.repeat(2, axis=1).repeat(2, axis=2)
    np.testing.assert_array_equal(out[:, :, :32], up(rgb))
    np.testing.assert_array_equal(out[:, :, 32:35], np.broadcast_to(SEPARATOR_RGB, (5, 24, 3, 3)))
    middle = out[:, :, 35:67]
    np.testing.assert_array_equal(middle[..., 0], up(true_mask) * 255)
    assert np.all(middle[..., 0] == middle[..., 2])  # grey
    right = out[:, :, 70:]
    np.testing.assert_array_equal(right[..., 1], up(np.rint(pred * 255).astype(np.uint8)))
    assert side_by_side(rgb, true_mask, pred, upscale=1, separator=0).shape == (5, 12, 48, 3)


def test_side_by_side_rejects_logits_and_bad_shapes():
    rgb, true_mask, pred = _clip()
    with pytest.raises(ValueError, match="pass probabilities, not logits"):
        side_by_side(rgb, true_mask, pred * 10 - 5)
    with pytest.raises(ValueError, match=r"masks must be \[T,H,W\]"):
        side_by_side(rgb, true_mask[:, :-1], pred)


def test_video_round_trip(tmp_path):
    t, h, w = 7, 32, 48
    yy, xx = np.mgrid[0:h, 0:w]
    frames = np.stack(
        [np.stack([xx * 5 + i * 10, yy * 7, np.full_like(xx, 200 - 20 * i)], -1) for i in range(t)]
    ).astype(np.uint8)  # smooth, distinct frames: a lossy codec keeps them close
    path = write_video(tmp_path / "videos" / "eval_100_seed0.mp4", frames, fps=15)
    assert path == tmp_path / "videos" / "eval_100_seed0.mp4"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
    cap = cv2.VideoCapture(str(path))
    read = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        read.append(frame[..., ::-1])  # BGR -> RGB
    cap.release()
    assert len(read) == t and read[0].shape == (h, w, 3)
    error = np.abs(np.stack(read).astype(int) - frames.astype(int)).mean(axis=(1, 2, 3))
    assert np.all(error < 8), error  # channel order and frame order survive
    assert np.abs(read[0].astype(int) - frames[-1].astype(int)).mean() > 30


def test_video_errors(tmp_path, monkeypatch):
    frames = np.zeros((2, 8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match=r"uint8 \[T,H,W,3\]"):
        write_video(tmp_path / "a.mp4", frames.astype(np.float32))

    class Closed:
        def __init__(self, *args):
            pass

        def isOpened(self):
            return False

    monkeypatch.setattr(cv2, "VideoWriter", Closed)
    with pytest.raises(RuntimeError, match="OpenCV could not open an mp4v video writer"):
        write_video(tmp_path / "b.mp4", frames)
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- plots


def _fake_workdir(
    root,
    name,
    method,
    task="walker-walk",
    offset=0.0,
    sweep=None,
    abs_cos=None,
    frames=(10_000, 20_000, 30_000),
    **fields,
):
    """A workdir as the trainer leaves it: config.json, and eval logs of 3 seeds per setting at
    `frames` (seed s of setting i returns offset + 100 i + frame / 100 + (0, 10, 50)[s]; with
    abs_cos, its |cos| column is abs_cos * (1, 2, 3)[s])."""
    workdir = root / name
    workdir.mkdir()
    config = {"seeds": 3, "agent": {"method": method}, "env": {"task": task}, **fields}
    config["sweep"] = sweep or {}
    (workdir / "config.json").write_text(json.dumps(config))
    names = [lane.name for lane in lanes.lanes(ConfigDict(config))]
    with RunLogger(workdir, len(names), tensorboard=False, names=names) as log:
        for frame in frames:
            returns = offset + frame / 100 + np.array([0.0, 10.0, 50.0] * (len(names) // 3))
            returns += np.repeat(100.0 * np.arange(len(names) // 3), 3)
            row = {"episode_return": returns, "cos_agent_env": 0.01}
            if abs_cos is not None:
                row["abs_cos_agent_env"] = abs_cos * np.tile([1.0, 2.0, 3.0], len(names) // 3)
            log.write("eval", frame, row)
            log.write("train", frame, {"fps": 900.0 + offset})
    return workdir


def test_plot_two_workdirs(tmp_path):
    dear = _fake_workdir(tmp_path, "a", "dear")
    drq = _fake_workdir(tmp_path, "b", "drqv2", offset=-50)
    (curve,) = plot.load_curves(dear, "episode_return")
    np.testing.assert_array_equal(curve.x, [10_000, 20_000, 30_000])
    np.testing.assert_array_equal(curve.y[:, 0], [100, 110, 150])  # seeds in rows
    out = plot.main([str(dear), str(drq), "--out", str(tmp_path / "c.png")])
    assert out == tmp_path / "c.png"
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 100 and image.std() > 0
    # One workdir: the PNG goes into it by default.
    assert plot.plot([dear], band="std") == dear / "curves.png"
    assert (dear / "curves.png").stat().st_size > 1000
    # A name without an extension: the PNG matplotlib writes, and the path said, end in .png.
    assert plot.plot([dear], tmp_path / "folder_like") == tmp_path / "folder_like.png"
    assert (tmp_path / "folder_like.png").is_file()


def test_plot_draws_each_experiments_mean_and_band(tmp_path, monkeypatch):
    """One panel for the task; per method a line at the mean over seeds and a band at mean +- the
    population std (or min to max); the legend names the method and its seed count. Seeds return
    frame / 100 + (0, 10, 50): mean + 20, population std sqrt(1400 / 3)."""
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to look at
    dear = _fake_workdir(tmp_path, "a", "dear")
    drq = _fake_workdir(tmp_path, "b", "drqv2", offset=-50)
    for band, below, above in (("std", (1400 / 3) ** 0.5, (1400 / 3) ** 0.5), ("minmax", 20, 30)):
        plot.plot([dear, drq], tmp_path / f"{band}.png", band=band)
        (ax,) = figures.pop().axes
        assert ax.get_title() == "walker-walk"
        assert [t.get_text() for t in ax.get_legend().get_texts()] == ["dear (n=3)", "drqv2 (n=3)"]
        assert len(ax.get_lines()) == len(ax.collections) == 2
        frames = [10_000, 20_000, 30_000]
        for line, band_area, offset in zip(ax.get_lines(), ax.collections, (0, -50)):
            mean = np.array([120.0, 220.0, 320.0]) + offset
            np.testing.assert_allclose(line.get_xdata(), frames)
            np.testing.assert_allclose(line.get_ydata(), mean)
            edge = band_area.get_paths()[0].vertices[:, 1]
            assert edge.min() == pytest.approx(mean[0] - below)
            assert edge.max() == pytest.approx(mean[-1] + above)


def test_seeds_of_one_experiment_pool_over_workdirs(tmp_path):
    """Runs of the same config with other config.seed values (other machines, other days) are
    one experiment: one curve holding all their seeds, one Table II row naming where its seeds
    come from, and how its runs evaluated and trained where they differ. Another method, or
    another learning setting, stays apart; the same seed twice is refused."""
    from configs import base

    def full(name, method, seed, changes=(), runs_per_gpu=None):
        c = base.make("walker", method)
        c.seeds, c.seed = 3, seed
        for dotted, value in changes:
            *parents, key = dotted.split(".")
            node = c
            for part in parents:
                node = node[part]
            node[key] = value
        workdir = _fake_workdir(tmp_path, name, method, offset=seed, **c.to_dict())
        summary = {"frames_per_seed": 30_000, "wall_s": 100.0 + seed, "action_dim": 6}
        summary["provenance"] = {"commit": f"{seed}" * 40, "device_kind": "H100", "jax": "0.11"}
        if runs_per_gpu is not None:  # older summaries have no such field: the run alone
            summary["runs_per_gpu"] = runs_per_gpu
        (workdir / "summary.json").write_text(json.dumps(summary))
        return workdir

    # A field a run may change without changing what it learns does not split an experiment;
    # nor does training beside another run on its GPU.
    a = full("a", "dear", 0)
    b = full("b", "dear", 7, [("num_eval_episodes", 5)], runs_per_gpu=2)
    other = full("c", "dear", 1, [("agent.beta", 10.0)])
    drq = full("d", "drqv2", 0)
    pools = plot.pools([a, drq, b, other])
    assert [len(p.seeds) for p in pools] == [6, 3, 3]
    assert pools[0].workdirs == [a, b]
    (curve,) = [plot.pool_curve(p, "episode_return") for p in pools[:1]]
    np.testing.assert_array_equal(curve.y[:, 0], [100, 110, 150, 107, 117, 157])
    rows = report.pooled_rows([a, b, drq], threshold=150.0)
    assert [(r["method"], r["seeds"]) for r in rows] == [("dear", 6), ("drqv2", 3)]
    row = rows[0]
    # b evaluated over 5 episodes where a took 10, and trained beside another run: pooled, and
    # said.
    assert row["run"] == (
        "a (3) + b (3) (evaluations differ: num_eval_episodes 10/5) (runs per GPU differ: 1/2)"
    )
    assert rows[1]["run"] == "d"  # one run: nothing differs
    finals = np.array([300, 310, 350, 307, 317, 357])
    assert row["final_return_mean"] == pytest.approx(finals.mean())
    assert row["final_return_std"] == pytest.approx(finals.std())
    # Returns of 150 reached at 10k by seeds 2 of both runs (150, 157), at 20k by the others.
    assert row["seeds_reaching_threshold"] == 6 and row["frames_to_threshold"] == 20_000
    assert row["s_per_1000_training"] == pytest.approx(np.median([1000 / 900, 1000 / 907]))
    assert row["s_per_1000_with_eval"] == pytest.approx(1000 * 207 / (2 * 3 * 30_000))
    sources = json.loads(row["sources"])
    assert [(s["workdir"], s["seeds"], s["commit"][:2]) for s in sources] == [
        (str(a), 3, "00"),
        (str(b), 3, "77"),
    ]
    assert row["code"] == "0000000 H100, 7777777 H100"
    # --at takes an evaluation that started just past its mark (10,016 for 10,000) as at it.
    at = [report.pooled_rows([a], 150.0, at=f)[0]["eval_frame"] for f in (19_500, 18_000)]
    assert at == [20_000, 10_000]
    out = report.main(["curves", str(a), str(b), str(drq), "--out", str(tmp_path / "p.png")])
    assert cv2.imread(str(out)).std() > 0
    twice = full("a_again", "dear", 0)
    with pytest.raises(
        ValueError,
        match="both trained seed 0 of config.seed=0 .* the same seed twice. Report one of them",
    ):
        plot.pools([a, twice])
    # One workdir named twice (overlapping globs; relative and absolute) counts once.
    (once,) = plot.pools([a, a, a.resolve()])
    assert len(once.seeds) == 3 and once.workdirs == [a]
    # Runs split by a field that is not a per-lane number are named by it, not both "dear".
    bf16 = full("e", "dear", 3, [("agent.compute_dtype", "bfloat16"), ("envs_per_seed", 16)])
    assert [(p.label, len(p.seeds)) for p in plot.pools([a, bf16])] == [
        ("agent.compute_dtype=float32 envs_per_seed=8", 3),
        ("agent.compute_dtype=bfloat16 envs_per_seed=16", 3),
    ]


def test_curves_pool_seeds_at_the_evaluations_they_share(tmp_path):
    """Seeds of runs whose evaluations start a few frames apart (10,000 and 10,016) share a
    point; a pooled curve ends at the last evaluation every seed has (a run stopped earlier
    ends it), so its mean is never over fewer seeds than its legend's n."""
    from configs import base

    def run(name, seed, frames):
        c = base.make("walker", "dear")
        c.seeds, c.seed = 3, seed
        return _fake_workdir(tmp_path, name, "dear", offset=seed, frames=frames, **c.to_dict())

    a = run("a", 0, (10_000, 20_000, 30_000))
    b = run("b", 1, (10_016, 20_016))  # stopped before its third evaluation
    (pool,) = plot.pools([a, b])
    curve = plot.pool_curve(pool, "episode_return")
    np.testing.assert_array_equal(curve.x, [10_000, 20_000])
    np.testing.assert_allclose(curve.y[:, 1], [200, 210, 250, 201.16, 211.16, 251.16])
    assert curve.cut  # the legend says where, and why, the line stops
    (alone,) = plot.load_curves(a, "episode_return")
    np.testing.assert_array_equal(alone.x, [10_000, 20_000, 30_000])
    assert not alone.cut
    # A seed with no evaluation yet leaves no point every seed has: said, not drawn empty.
    c = run("c", 2, ())
    with pytest.raises(FileNotFoundError, match="no eval log .*seed_0.eval.csv of .* 2 more"):
        plot.pool_curve(plot.pools([a, c])[0], "episode_return")


def test_table_and_claims_read_each_tasks_own_threshold_unless_given_one(tmp_path):
    """Frames to threshold: a return of 500 on a DMC task, in the kitchen a success rate of 1,
    unless a threshold is given. Seed s returns frame / 100 + (0, 10, 50)[s] at frames 0, 50,
    100: in the kitchen seeds 1 and 2 reach 1 at frame 0, seed 0 at 100 (median 0); on walker
    none reaches 500."""
    from configs import base, kitchen

    runs = []
    for name, c, action_dim in (
        ("light", kitchen.make("light", "dear"), 9),
        ("walker", base.make("walker", "dear"), 6),
        ("light_drqv2", kitchen.make("light", "drqv2"), 9),
    ):
        c.seeds = 3
        fields = c.to_dict()
        method, task = c.agent.method, fields.pop("env")["task"]
        workdir = _fake_workdir(tmp_path, name, method, task, frames=(0, 50, 100), **fields)
        summary = {"frames_per_seed": 100, "wall_s": 1.0, "action_dim": action_dim}
        (workdir / "summary.json").write_text(json.dumps(summary))
        runs.append(workdir)
    dear_runs = runs[:2]
    light, walker = report.pooled_rows(dear_runs, threshold=None)
    assert (light["threshold"], light["seeds_reaching_threshold"]) == (1.0, 3)
    assert light["frames_to_threshold"] == 0
    assert (walker["threshold"], walker["seeds_reaching_threshold"]) == (500.0, 0)
    assert (walker["frames_to_threshold"], walker["frames_to_threshold_lower"]) == (np.inf, 100)
    given = report.pooled_rows(dear_runs, threshold=1.5)
    assert [r["seeds_reaching_threshold"] for r in given] == [2, 2]
    assert given[0]["frames_to_threshold"] == 0
    _, text = report.runs_table(dear_runs, threshold=None)
    assert "| 0 (3/3 reach 1)" in text and "| not by 100 (0/3 reach 500)" in text
    # Seeds at 400k, 600k, 810k and two that stopped short of it at 790k and 890k: the median
    # lies between 790k (if the first stopped seed would have reached it next) and 810k.
    lower, median = claims.median_frames_to(
        [400e3, 600e3, 810e3, np.inf, np.inf], [1e6] * 3 + [790e3, 890e3]
    )
    assert report._frames_to(median, lower) == "790,000-810,000"
    assert report._frames_to(6e5, 6e5) == "600,000"
    # the kitchen's returns (success rates) with two decimals, a DMC task's with one
    assert f" {light['final_return_mean']:.2f} ± {light['final_return_std']:.2f} |" in text
    assert f" {walker['final_return_mean']:.1f} ± {walker['final_return_std']:.1f} |" in text
    # At 1.5 seeds 1 and 2 reach it at frame 0, seed 0 never: the median seed at 0. At 12 only
    # seed 2 does: the median seed had not by its last evaluation, at 100.
    (at_12,) = report.pooled_rows(dear_runs[:1], threshold=12)
    assert at_12["seeds_reaching_threshold"] == 1 and at_12["frames_to_threshold"] == np.inf
    assert at_12["frames_to_threshold_lower"] == 100
    rows = claims.check(runs)
    (light_efficiency,) = [
        r for r in rows if r["task"] == "kitchen-light" and r["claim"].endswith("than DrQ-v2")
    ]
    assert "(3/3 reach 1)" in light_efficiency["evidence"]
    assert light_efficiency["verdict"] == "does not hold"  # both at frame 0
    _, text = claims.claims_table(runs)
    assert "frames to a return of 500 (the kitchen's: 1, a success in every episode)" in text
    with pytest.raises(ValueError, match="last must be at least 1"):
        claims.check(runs, last=0)
    log = runs[0] / "seed_0" / "eval.csv"  # a run before its first evaluation's row
    log.write_text(log.read_text().splitlines()[0] + "\n")
    with pytest.raises(ValueError, match="seed_0/eval.csv has no evaluation yet"):
        report.pooled_rows(runs[:1], threshold=None)


def test_pools_are_labelled_by_the_numbers_that_set_them_apart(tmp_path):
    """A pool's label names the per-lane numbers its method reads that set it apart: what its
    run swept, a loss weight changed from the default, and what differs from another pool of
    its task and method (an int field and its float are one value). A weight the method does
    not read changes nothing: such runs pool. A sweep's lanes stay their own experiment."""
    from configs import base

    def run(name, seed, method="dear", sweep=None, task="walker", **agent):
        c = base.make(task, method)
        c.seeds, c.seed = 3, seed
        c.agent.update(agent)
        c.sweep.update(sweep or {})
        fields = c.to_dict()
        workdir = _fake_workdir(tmp_path, name, method, sweep=fields.pop("sweep"), **fields)
        summary = {"frames_per_seed": 30_000, "wall_s": 100.0, "action_dim": 6}
        (workdir / "summary.json").write_text(json.dumps(summary))
        return workdir

    def labels(*workdirs):
        return [(p.workdirs[0].name, p.label, p.changed) for p in plot.pools(workdirs)]

    plain, beta10 = run("plain", 0), run("beta10", 1, beta=10.0)
    assert labels(plain) == [("plain", "", ())]
    assert labels(beta10) == [("beta10", "beta=10", ("beta",))]
    assert labels(plain, beta10) == [("plain", "beta=100", ()), ("beta10", "beta=10", ("beta",))]
    steps = run("steps", 2, std_steps=1000)
    assert labels(plain, steps) == [
        ("plain", "std_steps=500000", ()),
        ("steps", "std_steps=1000", ()),
    ]
    # Swept: the sweep's keys, even one of a single value; its lanes are not the plain run's.
    sweep = run("sweep", 0, sweep={"alpha": "0", "beta": "0,100"})
    assert labels(sweep, plain) == [
        ("sweep", "alpha=0_beta=0", ("alpha", "beta")),
        ("sweep", "alpha=0_beta=100", ("alpha", "beta")),
        ("plain", "alpha=0.25_beta=100", ()),
    ]
    # DrQ-v2 reads neither weight: runs differing only in beta are one experiment.
    drq, drq_beta = run("drq", 0, method="drqv2"), run("drq_beta", 1, method="drqv2", beta=10.0)
    ((_, label, changed),) = labels(drq, drq_beta)
    assert (label, changed) == ("", ())
    assert len(plot.pools([drq, drq_beta])[0].seeds) == 6
    rows = report.pooled_rows([plain, beta10], threshold=150.0)
    assert [r["run"] for r in rows] == ["plain beta=100", "beta10 beta=10"]
    out = report.main(["curves", str(plain), str(beta10), "--out", str(tmp_path / "c.png")])
    assert cv2.imread(str(out)).std() > 0


def test_plot_draws_a_line_per_setting_of_a_sweep(tmp_path):
    run = _fake_workdir(tmp_path, "sweep", "dear", sweep={"beta": "0,100"})
    assert sorted(p.name for p in run.iterdir() if p.is_dir()) == [
        *(f"beta=0_seed_{s}" for s in range(3)),
        *(f"beta=100_seed_{s}" for s in range(3)),
    ]
    curves = plot.load_curves(run, "episode_return")
    assert [c.label for c in curves] == ["dear beta=0", "dear beta=100"]
    np.testing.assert_array_equal(curves[1].y[:, 0], [200, 210, 250])
    out = report.main(["curves", str(run), "--out", str(tmp_path / "beta.png")])
    assert cv2.imread(str(out)).std() > 0


def test_the_papers_claims_are_checked_per_task_on_the_seeds(tmp_path):
    """`report claims`: per task, each claim's figures from the seeds' logs (returns are
    each seed's mean over its last 2 evaluations here; frames to a return of 200) and whether
    it holds, with the spread. Returns at 10k/20k/30k frames: offset + 100/200/300 + (0, 10,
    50) per seed."""
    runs = [
        _fake_workdir(tmp_path, "dear", "dear", abs_cos=1e-3),
        _fake_workdir(tmp_path, "sear", "sear", offset=-50, abs_cos=2e-2),
        _fake_workdir(tmp_path, "ted", "ted", offset=-20),
        _fake_workdir(tmp_path, "drqv2", "drqv2", offset=-150),
    ]
    rows = {(r["claim"], r["task"]): r for r in claims.check(runs, threshold=200, last=2)}
    assert len(rows) == 6 and {t for _, t in rows} == {"walker-walk"}
    row = lambda claim: rows[claim, "walker-walk"]  # noqa: E731
    # DEAR's seeds: 250, 260, 300; SEAR's 200, 210, 250 (DEAR's lowest is not above SEAR's best)
    assert row("DEAR's return >= SEAR's") == {
        "claim": "DEAR's return >= SEAR's",
        "task": "walker-walk",
        "evidence": "DEAR 270.0 ± 21.6 (n=3) against SEAR 220.0 ± 21.6 (n=3)",
        "verdict": "holds (seeds overlap)",
    }
    assert row("TED's return > SEAR's")["verdict"] == "holds (seeds overlap)"  # 250 against 220
    # Frames to 200: DEAR 20k for every seed; TED and SEAR 30k, 30k, 20k; DrQ-v2 only its
    # third seed, at 30k: its median seed never reaches it in the 30k frames it ran.
    ted = row("DEAR >= 25% more sample-efficient than TED")
    assert ted["evidence"] == (
        "median frames to 200: DEAR 20k (3/3 reach 200), TED 30k (3/3 reach 200); ratio 0.67"
    )
    assert ted["verdict"] == "holds"
    drqv2 = row("DEAR >= 25% more sample-efficient than DrQ-v2")
    assert drqv2["evidence"].endswith("DrQ-v2 not by 30k (1/3 reach 200)")
    assert drqv2["verdict"] == "holds"  # 20k <= 0.75 x 30k, its median's lower bound
    # |cos| of the last evaluation: DEAR 1e-3 x (1, 2, 3), SEAR 2e-2 x (1, 2, 3)
    cos = row("DEAR's |cos| far below SEAR's")
    assert cos["evidence"] == "DEAR 2.0e-03, SEAR 4.0e-02: 20.0x (asked: >= 10x)"
    assert cos["verdict"] == "holds (seeds separate)"
    # Reversed, every DEAR seed above every SEAR seed: the seeds separate just as much.
    swapped = [
        _fake_workdir(tmp_path, "dear_high", "dear", abs_cos=2e-2),
        _fake_workdir(tmp_path, "sear_low", "sear", offset=-50, abs_cos=1e-3),
    ]
    cos = {r["claim"]: r for r in claims.check(swapped, threshold=200, last=2)}
    assert cos["DEAR's |cos| far below SEAR's"]["verdict"] == "does not hold (seeds separate)"

    # Higher thresholds: at 260 every DEAR and TED seed first reaches it at 30k (ratio 1.00);
    # at 300 every DEAR seed at 30k, one TED seed (its median seed never in its 30k frames);
    # at 360 no seed.
    def efficiency_vs_ted(threshold):
        rows = claims.check(runs, threshold=threshold, last=2)
        return {r["claim"]: r for r in rows}["DEAR >= 25% more sample-efficient than TED"]

    assert efficiency_vs_ted(260)["verdict"] == "does not hold"
    assert efficiency_vs_ted(260)["evidence"].endswith("ratio 1.00")
    assert efficiency_vs_ted(300)["verdict"] == "undecided: the runs are too short to tell"
    assert efficiency_vs_ted(360)["verdict"] == "undecided: neither's median seed reaches it"
    # Without SEAR, its claims say so; a second DEAR experiment on the task is refused, and so
    # are DEAR with a loss weight of its own and a sweep's lanes.
    without = {r["claim"]: r["verdict"] for r in claims.check(runs[::2], threshold=200)}
    assert without["DEAR's return >= SEAR's"] == "no data: no SEAR run"
    assert without["DEAR's |cos| far below SEAR's"] == "no data: no SEAR run"
    other = _fake_workdir(
        tmp_path, "dear_noisy", "dear", env={"task": "walker-walk", "mask": "noisy"}
    )
    with pytest.raises(ValueError, match="dear_noisy: a second experiment of dear on walker-walk"):
        claims.check([runs[0], other])
    beta = _fake_workdir(tmp_path, "dear_beta", "dear", agent={"method": "dear", "beta": 1.0})
    with pytest.raises(ValueError, match=r"dear_beta: dear with its own beta \(beta=1: a sweep "):
        claims.check([beta])
    sweep = _fake_workdir(tmp_path, "dear_sweep", "dear", sweep={"beta": "100"})
    with pytest.raises(ValueError, match=r"dear_sweep: dear with its own beta \(beta=100: "):
        claims.check([sweep])
    out = tmp_path / "claims"
    report.main(["claims", *map(str, runs), "--threshold", "200", "--last", "2", "--out", str(out)])
    saved = json.loads(out.with_suffix(".json").read_text())
    assert saved["threshold"] == 200 and len(saved["claims"]) == 6
    assert "| DEAR's return >= SEAR's" in out.with_suffix(".md").read_text()
    # A cell's own bars are escaped, so the Markdown table keeps its columns.
    lines = out.with_suffix(".md").read_text().splitlines()
    cos_row = next(line for line in lines if "far below" in line)
    assert "DEAR's \\|cos\\| far below" in cos_row
    assert cos_row.replace("\\|", "").count("|") == len(claims.COLUMNS) + 1


def paper_run(workdir, spec, seed, frames, seeds=1, summary=True, **fields):
    """A run's workdir as `report grid` reads it: config.json of `configs/paper.py:SPEC` with
    its seeds and the dotted `fields` set, and (with `summary`) the frames it reached."""
    from configs import paper

    config = paper.get_config(spec)
    config.seed, config.seeds = seed, seeds
    for key, value in fields.items():
        *parents, leaf = key.split(".")
        node = config
        for part in parents:
            node = node[part]
        node[leaf] = value
    workdir.mkdir(parents=True)
    (workdir / "config.json").write_text(json.dumps(config.to_dict()))
    if summary:
        (workdir / "summary.json").write_text(json.dumps({"frames_per_seed": frames}))
    return workdir


def test_grid_counts_each_cells_seeds_that_reached_the_frames(tmp_path):
    """`report grid`: a run counts in the cell of configs/paper.py whose config it has, but for
    its seeds, envs per seed, dtype and replay store (a field it lacks: its old behaviour,
    experiment.ADDED_FIELDS; a field since removed: passed over). A seed trained to the end twice counts once; a run stopped short is
    listed with its frames (a checkpoint: a resume command); free config.seed values fill the
    missing seeds that no resume brings, one seed-run each; every other run is named with the
    field that keeps it out."""

    def run(name, spec, seed, frames, seeds=1, summary=True, **fields):
        return paper_run(tmp_path / name, spec, seed, frames, seeds, summary, **fields)

    runs = [
        run("w_dear_s0", "walker,dear", 0, 1_000_000),
        # made when the config had a field since removed (experiment.REMOVED_FIELDS)
        run(
            "w_dear_s0_again",
            "walker,dear",
            0,
            1_000_000,
            envs_per_seed=16,
            **{"env.render.as_stepped": False},
        ),
        run(
            "w_dear_s1",
            "walker,dear",
            1,
            500_000,
            **{"agent.compute_dtype": "bfloat16", "env.render.as_stepped": False},
        ),
        run("w_dear_s4", "walker,dear", 4, 0, summary=False, **{"replay.capacity": 1000}),
        run("w_dear_refcos", "walker,dear", 5, 1_000_000, **{"agent.ortho_form": "reference_code"}),
        run("w_dear_full", "walker,dear,medium-full", 6, 1_000_000),
        run("w_dear_nstep", "walker,dear", 7, 1_000_000, **{"agent.nstep": 5}),
        run("c_sear", "cup,sear", 0, 1_000_000, seeds=2),
    ]
    (runs[2] / "checkpoints").mkdir()
    runs.append(runs[0])  # the same workdir twice counts once
    grid = report.grid_rows(runs, ["walker", "cup"], ["dear", "sear"], seeds=3)
    cell = {(r["task"], r["method"]): r for r in grid["cells"]}
    assert len(cell) == 4
    here = tmp_path.name
    assert cell["walker", "dear"] == {
        "task": "walker",
        "method": "dear",
        "spec": "walker,dear",
        "name": "walker_dear",
        "seeds_done": 1,
        "done": [f"{here}/w_dear_s0", f"{here}/w_dear_s0_again"],
        "short": [f"{here}/w_dear_s1 (500,000)", f"{here}/w_dear_s4 (no summary)"],
        "resume": [
            [
                "--config.agent.compute_dtype=bfloat16",
                "--config.seed=1",
                "--config.seeds=1",
                "--workdir",
                str(runs[2].resolve()),
            ]
        ],
        "missing": 2,
        "next_seeds": [2],  # s1's resume brings the other; 0, 1 and 4 are taken
        "total_frames": 1_000_000,
        "paces": [],  # its finished runs' summaries hold no wall clock
        "related_paces": [],  # nor those of its task and method in other settings
        "mixed": {"envs_per_seed": ["16", "8"]},  # its finished runs' choices differ
        "agreed": {},  # float32 and the replay's defaults, as the cell's config
    }
    assert (cell["cup", "sear"]["seeds_done"], cell["cup", "sear"]["next_seeds"]) == (2, [1])
    # A run that holds its workdir now (a live process in its lock) is running: not resumed,
    # and its seed is coming, so one new seed-run, not two, makes up the cell.
    with lock.WorkdirLock(runs[2]):
        busy = report.grid_rows(runs, ["walker"], ["dear"], seeds=3)["cells"][0]
    assert busy["short"][0] == f"{here}/w_dear_s1 (running)" and busy["resume"] == []
    assert busy["next_seeds"] == [2]
    # A checkpoint whose replay was in memory would resume on an empty replay: not resumed.
    lost = run("w_dear_s9", "walker,dear", 9, 700_000, **{"replay.disk": False})
    (lost / "checkpoints").mkdir()
    cell_lost = report.grid_rows([runs[0], lost], ["walker"], ["dear"], seeds=2)["cells"][0]
    assert cell_lost["short"] == [f"{here}/w_dear_s9 (700,000, its replay not kept)"]
    assert (cell_lost["resume"], cell_lost["next_seeds"]) == ([], [1])
    assert cell["walker", "sear"]["missing"] == 3 and cell["walker", "sear"]["next_seeds"] == [
        0,
        1,
        2,
    ]
    assert grid["outside"] == [
        f"{here}/w_dear_refcos: agent.ortho_form='reference_code' (the cell's: 'abs_cos')",
        f"{here}/w_dear_full: env.distraction_types='all' (the cell's: 'background')",
        f"{here}/w_dear_nstep: agent.nstep=5 (the cell's: 1)",
    ]
    text = report.grid_table(runs, ["walker", "cup"], ["dear", "sear"], seeds=3, frames=500_000)
    lines = text.splitlines()
    new_dear = [
        line
        for line in lines
        if line.startswith("python run.py") and "walker,dear --config.seed" in line
    ]
    assert new_dear == [  # at 500k s1 is done too: one seed is missing
        "python run.py --config configs/paper.py:walker,dear --config.seed=2 --config.seeds=1 "
        "--config.total_frames=500000 --workdir runs/walker_dear_s2"
    ]
    assert (
        "python run.py --config configs/paper.py:walker,sear --config.seed=0 --config.seeds=1 "
        "--config.total_frames=500000 --workdir runs/walker_sear_s0" in lines
    )
    text = report.grid_table(runs, ["walker"], ["dear"], seeds=3)
    assert "walker dear: envs_per_seed 16, 8" in text.splitlines()  # apart in `report table`
    assert (
        "python run.py --config configs/paper.py:walker,dear --config.agent.compute_dtype=bfloat16 "
        f"--config.seed=1 --config.seeds=1 --workdir {runs[2].resolve()}" in text
    )
    grid = report.grid_rows(runs, ["walker"], ["dear"], seeds=3)
    assert f"{here}/c_sear" in grid["elsewhere"] and f"{here}/w_dear_nstep" in grid["outside"][-1]
    assert not [name for name in grid["elsewhere"] if "/w_dear" in name]
    assert f"{len(grid['elsewhere'])} run(s) of other tasks or methods (not asked for)" in text
    # A task with its difficulty is a cell of that setting: the full suite's run counts there
    # (spaces in the task are dropped), a stopped one resumes with the setting in its config, and
    # new seed-runs say the setting in their config and workdir.
    stopped = run("w_dear_full_s8", "walker,dear,medium-full", 8, 300_000, progress=False)
    (stopped / "checkpoints").mkdir()
    both = report.grid_rows([*runs, stopped], ["walker", "walker, medium-full"], ["dear"], seeds=3)
    full = both["cells"][1]
    assert (full["task"], full["spec"], full["done"]) == (
        "walker,medium-full",
        "walker,dear,medium-full",
        [f"{here}/w_dear_full"],
    )
    assert not [line for line in both["outside"] if "w_dear_full" in line]
    assert both["cells"][0]["done"] == cell["walker", "dear"]["done"]  # the paper's, unchanged
    jobs = report.grid_jobs({"cells": [full], "outside": []}, 1_000_000)
    assert [job.args for job in jobs] == [
        (
            "--config",
            "configs/paper.py:walker,dear,medium-full",
            "--config.progress=False",
            "--config.seed=8",
            "--config.seeds=1",
            "--workdir",
            str(stopped.resolve()),
        ),
        (
            "--config",
            "configs/paper.py:walker,dear,medium-full",
            "--config.seed=0",
            "--config.seeds=1",
            "--workdir",
            "runs/walker_medium-full_dear_s0",
        ),
    ]
    taken = report.grid_rows(
        runs, ["walker,medium-full"], ["dear"], 2, taken={"walker_medium-full_dear_s0"}
    )
    assert taken["cells"][0]["next_seeds"] == [1]
    text = report.grid_table(runs, ["walker,medium-full"], ["dear"], seeds=2)
    assert "| walker,medium-full | dear   |" in text
    assert "--workdir runs/walker_medium-full_dear_s0" in text
    # One setting twice (another spelling, paper.py's default difficulty) would fill one cell
    # while the other asked for seeds forever: refused.
    for twice in (["walker,medium-full", "walker , medium-full"], ["walker", "walker,medium"]):
        with pytest.raises(ValueError, match="are one setting: give it once"):
            report.grid_rows(runs, twice, ["dear"])
    with pytest.raises(ValueError, match="unknown difficulty 'loud'"):
        report.grid_rows(runs, ["walker,loud"], ["dear"])


def test_grid_cells_of_a_weight_setting(tmp_path):
    """A task with WEIGHT=VALUE parts makes cells of that setting for the methods that read the
    weight (alpha: DEAR and SEAR; beta: DEAR): runs given that weight count there (to --frames:
    a 1M run counts at 500k), the paper's DEAR runs in beta=100's cell, which is the paper's
    own (given twice: refused); new seed-runs carry the setting in their spec and workdir. A
    replay sampling (sampling=episode) makes cells of every method."""
    from configs import paper

    c = paper.get_config("walker,dear,alpha=0,beta=0")
    assert (c.agent.alpha, c.agent.beta) == (0.0, 0.0)
    assert paper.get_config("walker,dear,std_steps=1000").agent.std_steps == 1000  # an int field
    assert paper.get_config("light,drqv2,noise_hold=10").agent.noise_hold == 10
    sampled = paper.get_config("light,drqv2,noise_hold=10,sampling=episode")
    assert (sampled.replay.sampling, sampled.agent.noise_hold) == ("episode", 10)
    assert paper.get_config("light,drqv2").replay.sampling == "uniform"
    for bad, message in (
        ("light,dear,sampling=episodes", "the replay's sampling is one of uniform, episode"),
        ("walker,drqv2,beta=1", r"'beta=1' in 'walker,drqv2,beta=1': drqv2 does not read beta \("),
        ("walker,dear,gamma=1", "unknown setting 'gamma' .*; valid: alpha, beta, "),
        ("walker,dear,beta=x", "'beta=x' in .*: give a number, e.g. beta=10"),
        ("walker,dear,beta=", "'beta=' in .*: give a number"),
        ("walker,dear,beta=1,beta=2", "beta given twice in 'walker,dear,beta=1,beta=2'"),
        ("walker,dear,std_steps=10.5", "std_steps is a whole number"),
        ("walker,beta=1,dear", r"give TASK,METHOD\[,DIFFICULTY\[,MASK\]\]\[,WEIGHT=VALUE...\]"),
    ):
        with pytest.raises(ValueError, match=message):
            paper.get_config(bad)

    def run(name, spec, seed, frames):
        return paper_run(tmp_path / name, spec, seed, frames)

    runs = [
        run("dear_s0", "walker,dear", 0, 1_000_000),
        run("beta10_s0", "walker,dear,beta=10", 0, 500_000),
        run("alpha0_sear_s0", "walker,sear,alpha=0", 0, 500_000),
        run("beta10_short", "walker,dear,beta=10", 1, 200_000),
        run("episode_sear_s0", "walker,sear,sampling=episode", 0, 500_000),
    ]
    tasks = ["walker,beta=10", "walker,beta=100", "walker,alpha=0", "walker,sampling=episode"]
    grid = report.grid_rows(runs, tasks, paper.METHODS, seeds=2, frames=500_000)
    got = {
        (r["task"], r["method"]): (r["done"], r["short"], r["next_seeds"]) for r in grid["cells"]
    }
    here = tmp_path.name
    assert got == {
        ("walker,beta=10", "dear"): (
            [f"{here}/beta10_s0"],
            [f"{here}/beta10_short (200,000)"],
            [2],
        ),
        ("walker,beta=100", "dear"): ([f"{here}/dear_s0"], [], [1]),
        ("walker,alpha=0", "dear"): ([], [], [0, 1]),
        ("walker,alpha=0", "sear"): ([f"{here}/alpha0_sear_s0"], [], [1]),
        # not a weight: every method's cell
        ("walker,sampling=episode", "sear"): ([f"{here}/episode_sear_s0"], [], [1]),
        **{("walker,sampling=episode", m): ([], [], [0, 1]) for m in ("drqv2", "dear", "ted")},
    }
    jobs = report.grid_jobs(grid, 500_000)
    assert jobs[0].name == "walker_beta=10_dear_s2"
    assert jobs[0].args[:2] == ("--config", "configs/paper.py:walker,dear,beta=10")
    assert "--config.total_frames=500000" in jobs[0].args
    with pytest.raises(ValueError, match="are one setting: give it once"):
        report.grid_rows(runs, ["walker", "walker,beta=100"], ["dear"])
    with pytest.raises(ValueError, match="task 'walker,beta=1': none of drqv2, ted reads beta"):
        report.grid_rows(runs, ["walker,beta=1"], ["drqv2", "ted"])


def test_cosines_set_the_evaluation_and_the_training_log_side_by_side(tmp_path, capsys):
    """`report cosines`, per seed: the last evaluation's cosines, and the training log's last
    rows (each the mean over the updates since the row before: updates x batch samples),
    read up to the last evaluation (or --at). Train rows every 5k frames, 100 updates each at
    batch 4; seed s's signed cos alternates +-(s + 1) 1e-6 from +, its |cos| is 1e-3."""
    run = _fake_workdir(tmp_path, "dear", "dear", agent={"method": "dear", "batch_size": 4})
    for s in range(3):
        lines = ["frame,updates,cos_agent_env,abs_cos_agent_env"] + [
            f"{frame},{100 * (i + 1)},{(-1) ** i * (s + 1) * 1e-6},0.001"
            for i, frame in enumerate(range(5_000, 30_001, 5_000))
        ]
        (run / f"seed_{s}" / "train.csv").write_text("\n".join(lines) + "\n")
    rows = report.cosine_rows([run], rows=3)
    assert [r["seed"] for r in rows] == ["dear/seed_0", "dear/seed_1", "dear/seed_2"]
    # the last 3 rows (20k, 25k, 30k: signs -, +, -); the first row has no row before it
    assert rows[1]["train_frames"] == "20,000-30,000"
    assert rows[1]["train_cos"] == pytest.approx(-2e-6 / 3)
    assert rows[1]["train_cos_row_median_abs"] == pytest.approx(2e-6)
    assert rows[1]["train_abs_cos"] == pytest.approx(1e-3)
    assert rows[1]["samples_per_row"] == 400
    assert (rows[1]["eval_frame"], rows[1]["eval_cos"]) == (30_000, 0.01)
    # up to 20k frames: the evaluation there, the rows 15k and 20k (signs +, -)
    early = report.cosine_rows([run], rows=2, at=20_000)[2]
    assert (early["eval_frame"], early["train_frames"]) == (20_000, "15,000-20,000")
    assert early["train_cos"] == pytest.approx(0.0, abs=1e-15)
    report.main(["cosines", str(run), "--rows", "3", "--out", str(tmp_path / "cos")])
    assert "| dear/seed_2 " in capsys.readouterr().out
    assert "samples per row" in (tmp_path / "cos.md").read_text()
    with pytest.raises(ValueError, match="rows=0: give at least 1"):
        report.cosine_rows([run], rows=0)
    # a row of episode returns alone (no metrics, no update since the row before) is skipped
    path = run / "seed_1" / "train.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines[:-1], "27500,500,,", lines[-1]]) + "\n")
    assert report.cosine_rows([run], rows=3)[1] == rows[1]
    # a log without the columns is named
    drq = _fake_workdir(tmp_path, "drqv2", "drqv2", agent={"method": "drqv2", "batch_size": 4})
    with pytest.raises(ValueError, match="drqv2/seed_0/train.csv has no abs_cos_agent_env, "):
        report.cosine_rows([drq])


def test_claims_compare_both_sides_at_the_shortest_runs_last_evaluation(tmp_path):
    """A SEAR run stopped at 20,016 frames against DEAR's to 30k: DEAR's returns and |cos| are
    taken up to SEAR's last evaluation (DEAR's at 20,000 is the same point), not at its own end,
    where it would lead."""
    dear = _fake_workdir(tmp_path, "dear", "dear", abs_cos=1e-3)
    sear = _fake_workdir(tmp_path, "sear", "sear", offset=50, abs_cos=2e-3, frames=(10_000, 20_016))
    rows = {r["claim"]: r for r in claims.check([dear, sear], threshold=200, last=1)}
    # At 20k DEAR's seeds return 200, 210, 250; SEAR's 250.16, 260.16, 300.16 (at 30k DEAR's
    # 300, 310, 350 would be ahead).
    ahead = rows["DEAR's return >= SEAR's"]
    assert ahead["evidence"] == (
        "DEAR 220.0 ± 21.6 (n=3) against SEAR 270.2 ± 21.6 (n=3), at 20k (the shortest run's "
        "last evaluation)"
    )
    assert ahead["verdict"] == "does not hold (seeds separate)"  # 250.16 > 250
    assert rows["DEAR's |cos| far below SEAR's"]["evidence"].endswith(
        "2.0x (asked: >= 10x), at 20k (the shortest run's last evaluation)"
    )
    # Evaluated every 600 frames (the smoke config's), runs 600 apart end at different
    # evaluations: compared at the shorter's, not within plot.SLACK's 1,000 frames.
    often = [
        _fake_workdir(tmp_path, f"{m}_600", m, frames=f, eval_every_frames=600, offset=o)
        for m, f, o in (("dear", (600, 1200, 1800), 0.0), ("sear", (600, 1200), 50.0))
    ]
    ahead = {r["claim"]: r for r in claims.check(often, threshold=200, last=1)}
    assert ahead["DEAR's return >= SEAR's"]["evidence"] == (
        "DEAR 32.0 ± 21.6 (n=3) against SEAR 82.0 ± 21.6 (n=3), at 1k (the shortest run's last "
        "evaluation)"
    )
    # Runs that end at the same evaluation say nothing of frames.
    same = {
        r["claim"]: r
        for r in claims.check([dear, _fake_workdir(tmp_path, "s2", "sear")], threshold=200)
    }
    assert same["DEAR's return >= SEAR's"]["evidence"].endswith("(n=3)")


def test_sample_efficiency_is_decided_only_where_the_censored_median_allows():
    """A seed that never reached the threshold took more than its last evaluated frame: the
    median over seeds lies between bounds, and the claim (DEAR's median <= 0.75 x the
    baseline's) is decided only where the bounds decide it."""

    def seeds(frames_to, last):
        n = len(frames_to)
        return claims.Seeds(np.zeros(n), np.array(frames_to, float), np.full(n, last), np.ones(n))

    def verdict(dear, baseline):
        return claims._efficiency("t", "ted", {"dear": dear, "ted": baseline}, 500)

    never = np.inf
    # TED's median of (10k, never by 100k) is between 55k and infinity: DEAR's 70k may or
    # may not be 25% below it; against a baseline that ran to 1M it is.
    row = verdict(seeds([70e3, 70e3], 1e6), seeds([10e3, never], 100e3))
    assert row["verdict"] == "undecided: the runs are too short to tell"
    assert row["evidence"] == (
        "median frames to 500: DEAR 70k (2/2 reach 500), TED not by 55k (1/2 reach 500)"
    )
    assert verdict(seeds([70e3, 70e3], 1e6), seeds([10e3, never], 1e6))["verdict"] == "holds"
    # DEAR's (10k, never by 100k) against TED's 900k: at most 0.75 x 900k needs more frames
    assert verdict(seeds([10e3, never], 100e3), seeds([900e3] * 2, 1e6))["verdict"] == (
        "undecided: the runs are too short to tell"
    )
    # DEAR never by 1M against TED at 800k: 1M > 0.75 x 800k
    row = verdict(seeds([never] * 3, 1e6), seeds([800e3] * 3, 1e6))
    assert row["verdict"] == "does not hold"
    # three seeds, one censored beyond the other two: the median is exact (ratio 0.60)
    row = verdict(seeds([300e3, 300e3, never], 1e6), seeds([500e3, 500e3, 600e3], 1e6))
    assert row["verdict"] == "holds" and row["evidence"].endswith("; ratio 0.60")
    # a baseline reaching T at its first evaluation (frame 0) leaves nothing to beat
    row = verdict(seeds([0.0] * 3, 1e6), seeds([0.0, 0.0, 10e3], 1e6))
    assert row["verdict"] == "does not hold" and "ratio" not in row["evidence"]


def test_table_ii_reads_logs_older_than_a_column_and_marks_mixed_frames():
    old = {"frame": np.array([0.0, 10.0]), "cos_agent_env": np.array([0.2, 0.1])}
    new = {**old, "abs_cos_agent_env": np.array([0.3, 0.4])}
    assert report._last_mean([new, new], "abs_cos_agent_env") == pytest.approx(0.4)
    assert np.isnan(report._last_mean([old, new], "abs_cos_agent_env"))
    assert report._last_mean([old, new], "cos_agent_env") == pytest.approx(0.1)
    assert report._frames(10_000, 10_000) == "10,000"
    assert report._frames(5_000, 10_000) == "5,000-10,000"


def test_task_name_says_the_distraction():
    assert plot.task_name({"env": {"task": "walker-walk", "distraction": "none"}}) == "walker-walk"
    medium = {"env": {"task": "finger-spin", "distraction": "medium"}}
    # Runs logged before distraction_types existed ran the full suite.
    assert plot.task_name(medium) == "finger-spin, distracting medium full suite"
    medium["env"]["distraction_types"] = "background"
    assert plot.task_name(medium) == "finger-spin, distracting medium background"
    medium["env"] |= {"distraction_types": "camera,color", "dynamic": True}
    assert plot.task_name(medium) == "finger-spin, distracting medium color+camera dynamic"


def test_plot_labels():
    curves = [
        plot.Curve(pathlib.Path(p), task, m, np.zeros(1), np.zeros((1, 1)))
        for p, task, m in [
            ("r/x", "walker", "dear"),
            ("r/y", "walker", "dear"),
            ("r/z", "cup", "ted"),
        ]
    ]
    plot._set_labels(curves)
    assert [c.label for c in curves] == ["walker dear (x)", "walker dear (y)", "cup ted"]


def test_plot_errors(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "config.json").write_text('{"seeds": 1}')
    with pytest.raises(FileNotFoundError, match=r"no eval log .*seed_0.eval\.csv"):
        plot.plot([empty])
    with pytest.raises(
        FileNotFoundError, match="nowhere does not exist: give the workdir of a run"
    ):
        plot.plot([tmp_path / "nowhere"])
    (tmp_path / "not_a_run").mkdir()
    with pytest.raises(FileNotFoundError, match="config.json not found: give the workdir of a run"):
        plot.plot([tmp_path / "not_a_run"])
    # A folder of runs given as one: the error names them and how to give them.
    with pytest.raises(
        FileNotFoundError, match=r"holds 1 runs \(empty\): give them, e\.g\. .*/\*/"
    ):
        plot.plot([tmp_path])
    with pytest.raises(FileNotFoundError, match="summary.json not found: run.py writes it at"):
        report.pooled_rows([empty], threshold=None)
    with pytest.raises(SystemExit):
        plot.main([str(empty)])
    assert "seed_0/eval.csv" in capsys.readouterr().err
    run = _fake_workdir(tmp_path, "run", "dear")
    with pytest.raises(KeyError, match="no column 'success'; columns: frame, episode_return"):
        plot.plot([run], metric="success")
