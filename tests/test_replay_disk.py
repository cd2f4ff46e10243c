"""The replay on disk: chunks written as rows fill, a checkpoint's partial chunk, and the device
replay rebuilt from them (ring wrap-around included), ignoring files written after the checkpoint."""

import shutil

import jax
import numpy as np
import pytest

from dear_jax import replay, replay_disk

SEEDS, ENVS, ROWS, CHUNK = 2, 3, 10, 4
FRAME = (4, 4, 3)
_add = jax.jit(jax.vmap(replay.add))


def _empty():
    return replay.init(ROWS * ENVS, ENVS, FRAME, 2, leading=(SEEDS,))


def _fill(buffer, store, rng, start, end):
    """Rows start..end-1 of random timesteps (episodes of random lengths), chunked as they fill."""
    for g in range(start, end):
        buffer = _add(
            buffer,
            rng.integers(0, 256, (SEEDS, ENVS, *FRAME), dtype=np.uint8),
            rng.integers(0, 2, (SEEDS, ENVS, *FRAME[:2]), dtype=np.uint8),
            rng.uniform(-1, 1, (SEEDS, ENVS, 2)).astype(np.float32),
            rng.uniform(0, 1, (SEEDS, ENVS)).astype(np.float32),
            np.ones((SEEDS, ENVS), np.float32),
            rng.uniform(size=(SEEDS, ENVS)) < 0.2,
        )
        store.added(buffer, g + 1)
    return buffer


def _meta(buffer):
    return {"episodes_started": buffer.episodes_started, "pos": buffer.pos, "size": buffer.size}


def _assert_equal(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("checkpoint_row", [7, 23])  # ring not yet full / wrapped twice
def test_round_trip_from_chunks_and_the_checkpoints_partial_chunk(tmp_path, checkpoint_row):
    rng = np.random.default_rng(checkpoint_row)
    store = replay_disk.ChunkStore(tmp_path, SEEDS, ROWS, CHUNK)
    buffer = _fill(_empty(), store, rng, 0, checkpoint_row)
    store.save_partial(buffer, checkpoint_row)  # what a checkpoint does before committing
    saved = jax.tree.map(np.asarray, buffer)
    buffer = _fill(buffer, store, rng, checkpoint_row, checkpoint_row + 9)  # then lost
    store.close()
    names = {p.name for p in (tmp_path / "seed_1").iterdir()}
    assert replay_disk.file_name(checkpoint_row - checkpoint_row % CHUNK, checkpoint_row) in names

    resumed = replay_disk.ChunkStore(tmp_path, SEEDS, ROWS, CHUNK)
    resumed.forget_after(checkpoint_row)
    assert all(end <= checkpoint_row for _, end, _ in replay_disk.list_files(tmp_path / "seed_0"))
    rebuilt = resumed.restore(_empty(), checkpoint_row).replace(**_meta(saved))
    _assert_equal(rebuilt, saved)

    # Files that end before the ring's oldest live row are deleted; the rebuild still works.
    resumed.prune(checkpoint_row, {checkpoint_row})
    ends = [end for _, end, _ in replay_disk.list_files(tmp_path / "seed_0")]
    assert min(ends) > checkpoint_row - ROWS
    _assert_equal(resumed.restore(_empty(), checkpoint_row).replace(**_meta(saved)), saved)
    # The resumed run writes the rest of the unfinished chunk again, in full.
    _fill(rebuilt, resumed, rng, checkpoint_row, checkpoint_row + CHUNK)
    resumed.close()
    files = replay_disk.list_files(tmp_path / "seed_0")
    assert any(end - start == CHUNK and start <= checkpoint_row < end for start, end, _ in files)


def test_every_kept_checkpoint_finds_its_whole_replay(tmp_path):
    """Checkpoints every 4-6 rows, the last 3 kept, the ring (10 rows) wrapped past the oldest
    kept one's: pruning after each save keeps the rows of every kept checkpoint, and a resume
    from each (the files written after it forgotten) rebuilds its replay as it was."""
    rng = np.random.default_rng(5)
    store = replay_disk.ChunkStore(tmp_path / "replay", SEEDS, ROWS, CHUNK)
    buffer, saved, kept, row = _empty(), {}, [], 0
    for checkpoint_row in (6, 11, 15, 21, 26):
        buffer = _fill(buffer, store, rng, row, checkpoint_row)
        row = checkpoint_row
        store.save_partial(buffer, checkpoint_row)
        saved[checkpoint_row] = jax.tree.map(np.asarray, buffer)
        kept = [*kept, checkpoint_row][-3:]
        store.prune(checkpoint_row, set(kept))
    store.close()
    for checkpoint_row in kept:
        copy = tmp_path / f"resume_{checkpoint_row}"
        shutil.copytree(tmp_path / "replay", copy)
        resumed = replay_disk.ChunkStore(copy, SEEDS, ROWS, CHUNK)
        resumed.forget_after(checkpoint_row)
        rebuilt = resumed.restore(_empty(), checkpoint_row)
        resumed.close()
        _assert_equal(rebuilt.replace(**_meta(saved[checkpoint_row])), saved[checkpoint_row])


def test_missing_rows_are_a_clear_error(tmp_path):
    store = replay_disk.ChunkStore(tmp_path, SEEDS, ROWS, CHUNK)
    with pytest.raises(FileNotFoundError, match="replay rows from 0 of seed 0 are missing"):
        store.restore(_empty(), 5)
    store.close()


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_damaged_replay_file_is_named_and_kept(tmp_path, damage):
    """A chunk cut short or with bytes changed: the resume's error names the file, its rows and
    the two ways on; the file itself is left as it was."""
    store = replay_disk.ChunkStore(tmp_path, SEEDS, ROWS, CHUNK)
    _fill(_empty(), store, np.random.default_rng(0), 0, CHUNK)
    store.close()
    (_, _, path), *_ = replay_disk.list_files(tmp_path / "seed_0")
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[len(data) // 3 : len(data) // 3 + 64] = bytes(64)
    path.write_bytes(bytes(data))
    store = replay_disk.ChunkStore(tmp_path, SEEDS, ROWS, CHUNK)
    with pytest.raises(replay_disk.MissingReplayError) as error:
        store.restore(_empty(), CHUNK)
    store.close()
    message = str(error.value)
    assert f"replay file {path} cannot be read" in message
    assert f"rows 0..{CHUNK - 1} of seed 0" in message and "replay.disk=False" in message
    assert path.read_bytes() == bytes(data)


def test_disk_check_names_the_numbers_and_the_field(tmp_path):
    with pytest.raises(OSError, match=r"GiB more .* GiB is free .*set replay\.disk=False"):
        replay_disk.check_disk(tmp_path, 10**18)
    more, free = replay_disk.check_disk(tmp_path, 1000)
    assert more == 1000 and free > 1000
    bound = replay_disk.disk_bound(
        num_seeds=3,
        rows=100,
        chunk_rows=10,
        num_envs=8,
        entry_bytes=1000,
        rows_between_checkpoints=50,
        keep_checkpoints=3,
        total_rows=10**6,
    )
    # Per seed: the buffer's rows, the rows written between two checkpoints (kept until the
    # next), and the chunks the kept checkpoints' partial files and the writer hold.
    assert bound == 3 * (100 + 3 * 50 + 5 * 10) * 8 * 1000
    # A run shorter than that writes every row once, plus at most one partial chunk.
    short = dict(num_seeds=3, rows=100, chunk_rows=10, num_envs=8, entry_bytes=1000)
    short.update(rows_between_checkpoints=50, keep_checkpoints=3, total_rows=120)
    assert replay_disk.disk_bound(**short) == 3 * (120 + 4 * 10) * 8 * 1000
