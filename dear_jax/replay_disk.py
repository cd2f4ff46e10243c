"""The replay on disk: each seed's rows written in compressed chunks as they fill, for resumes.

The device replay (`dear_jax/replay.py`) is a ring of T rows; row g of a run (g counts the rows
added since its start) lives in ring row g % T. Here rows are grouped in chunks of C rows
(`chunk_entries` / E, at most T); when the run has added rows [kC, (k+1)C), those rows of every
seed are copied off the accelerator and a background thread writes one file per seed,

    <dir>/seed_<s>/<first row>-<end row>.npz   (np.savez_compressed; end row exclusive)

holding frames, masks, actions, rewards, discounts and episode ids of the rows, written to a
temporary name and renamed, so a file is either whole or absent. No checkpoint writes the
replay at once; a checkpoint at row G first waits for the queued chunks, then writes the rows of
the unfinished chunk [floor(G/C) C, G) the same way (a partial file), and only then commits.

Resume from a checkpoint at row G: files ending after G were written after that checkpoint and
are deleted; the ring's live rows [max(0, G - T), G) are read back from the files, each row from
the file that ends last (full chunk or partial one), and put into an empty device replay.
Files that end at or before G - T of the oldest kept checkpoint are out of every kept ring and
are deleted (so every checkpoint orbax keeps finds its whole replay); so are partial files of
checkpoints that orbax no longer keeps.

Disk: at most (T + rows between checkpoints per checkpoint kept + a chunk per checkpoint kept + 2
chunks) rows per seed at the uncompressed size (`disk_bound`); the trainer checks this against
free space.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import logging
import math
import os
import pathlib
import re
import shutil
import zipfile
import zlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dear_jax import replay

log = logging.getLogger(__name__)

FIELDS = ("frames", "masks", "actions", "rewards", "discounts", "episode")
_NAME = re.compile(r"^(\d+)-(\d+)\.npz$")


def file_name(start: int, end: int) -> str:
    return f"{start:012d}-{end:012d}.npz"


def list_files(seed_dir: pathlib.Path) -> list[tuple[int, int, pathlib.Path]]:
    """(start, end, path) of every complete chunk file of one seed, sorted."""
    out = []
    if seed_dir.is_dir():
        for p in seed_dir.iterdir():
            m = _NAME.match(p.name)
            if m:
                out.append((int(m.group(1)), int(m.group(2)), p))
    return sorted(out)


def bytes_on_disk(directory: pathlib.Path) -> int:
    if not directory.is_dir():
        return 0
    return sum(p.stat().st_size for p in directory.rglob("*.npz"))


def disk_bound(
    *,
    num_seeds: int,
    rows: int,
    chunk_rows: int,
    num_envs: int,
    entry_bytes: int,
    rows_between_checkpoints: int,
    keep_checkpoints: int,
    total_rows: int,
) -> int:
    """Upper bound of the bytes the chunk files of a run take (uncompressed sizes)."""
    per_seed = rows + keep_checkpoints * rows_between_checkpoints
    per_seed += (keep_checkpoints + 2) * chunk_rows
    per_seed = min(per_seed, total_rows + (keep_checkpoints + 1) * chunk_rows)
    return num_seeds * per_seed * num_envs * entry_bytes


class DiskSpaceError(OSError):
    """The replay on disk would not fit on the workdir's disk."""


class MissingReplayError(FileNotFoundError):
    """A checkpoint's replay rows are not on disk (deleted, damaged, or never written there)."""


def check_disk(directory: pathlib.Path, need: int, *, headroom: float = 0.9) -> tuple[int, int]:
    """(bytes still to write, free bytes); raise DiskSpaceError naming the numbers unless they
    fit."""
    directory.mkdir(parents=True, exist_ok=True)
    more = max(0, need - bytes_on_disk(directory))
    free = shutil.disk_usage(directory).free
    if more > headroom * free:
        gib = 2**30
        raise DiskSpaceError(
            f"the replay on disk ({directory}) may need {more / gib:.2f} GiB more "
            f"(uncompressed bound: ring + rows between checkpoints), but only {free / gib:.2f} GiB "
            f"is free there and {headroom:.0%} of it may be used; set replay.disk=False (a resume "
            "then refills the replay), lower replay.capacity or checkpoint_every_frames, or use a "
            "--workdir on a larger disk"
        )
    return more, free


@functools.partial(jax.jit, static_argnames="length")
def _take_rows(buffer: replay.ReplayState, start, length: int) -> dict:
    """Rows start..start+length-1 (mod T) of every seed: {field: [S, length, E, ...]}."""
    rows = buffer.frames.shape[1]
    idx = (start + jnp.arange(length)) % rows
    return {f: jnp.take(getattr(buffer, f), idx, axis=1) for f in FIELDS}


@functools.partial(jax.jit, donate_argnums=0)
def _put_rows(buffer: replay.ReplayState, seed, idx, data: dict) -> replay.ReplayState:
    """buffer[seed, idx] = data per field; idx entries out of range (padding) are dropped."""
    return buffer.replace(
        **{f: getattr(buffer, f).at[seed, idx].set(data[f], mode="drop") for f in FIELDS}
    )


def _write_npz(path: pathlib.Path, arrays: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


@dataclasses.dataclass
class ChunkStore:
    """Writes and reads back the chunk files of all seeds of one run in `directory`; with several
    processes, those of this process's block of seeds (`first_seed`: the global index of its first,
    for folder names; `read`: a [S, ...] device array's block of this process on the host)."""

    directory: pathlib.Path
    num_seeds: int
    rows: int  # T, ring rows of the device replay
    chunk_rows: int  # C
    first_seed: int = 0
    read: Callable = np.asarray

    def __post_init__(self):
        self.directory = pathlib.Path(self.directory)
        self.chunk_rows = max(1, min(int(self.chunk_rows), self.rows))
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="replay-disk")
        self._pending: list[concurrent.futures.Future] = []
        for s in range(self.num_seeds):
            self.seed_dir(s).mkdir(parents=True, exist_ok=True)
            for tmp in self.seed_dir(s).glob(".*.tmp"):  # a write killed half way
                tmp.unlink()

    def seed_dir(self, seed: int) -> pathlib.Path:
        return self.directory / f"seed_{self.first_seed + seed}"

    # -- writing -----------------------------------------------------------------------------
    def added(self, buffer: replay.ReplayState, rows_added: int) -> None:
        """Call after each add: queues the chunk that `rows_added` rows just completed, if any."""
        if rows_added % self.chunk_rows == 0:
            self._queue(buffer, rows_added - self.chunk_rows, rows_added)

    def _queue(self, buffer: replay.ReplayState, start: int, end: int) -> None:
        self._raise_failed()
        # Always a whole chunk's window (one compiled program); a partial one is cut on the host.
        rows = _take_rows(buffer, start % self.rows, self.chunk_rows)
        for x in rows.values():
            x.copy_to_host_async()
        self._pending.append(self._executor.submit(self._write, rows, start, end))

    def _write(self, rows: dict, start: int, end: int) -> None:
        host = {f: self.read(x)[:, : end - start] for f, x in rows.items()}
        for s in range(self.num_seeds):
            _write_npz(self.seed_dir(s) / file_name(start, end), {f: v[s] for f, v in host.items()})

    def _raise_failed(self) -> None:
        done = [f for f in self._pending if f.done()]
        self._pending = [f for f in self._pending if not f.done()]
        for f in done:
            f.result()  # re-raises a failed write

    def flush(self) -> None:
        """Block until every queued chunk is on disk."""
        pending, self._pending = self._pending, []
        for f in pending:
            f.result()

    def save_partial(self, buffer: replay.ReplayState, rows_added: int) -> None:
        """For a checkpoint at `rows_added`: every row up to it on disk when this returns."""
        start = rows_added - rows_added % self.chunk_rows
        if start < rows_added:
            self._queue(buffer, start, rows_added)
        self.flush()

    # -- cleaning ----------------------------------------------------------------------------
    def forget_after(self, rows_added: int) -> None:
        """Delete files that end after `rows_added` (written after the checkpoint resumed)."""
        for s in range(self.num_seeds):
            for _, end, path in list_files(self.seed_dir(s)):
                if end > rows_added:
                    path.unlink()

    def prune(self, latest_rows: int, kept_rows: set[int]) -> None:
        """Delete files out of the ring of every kept checkpoint and partial files of checkpoints
        no longer kept (`kept_rows`: the row counts of kept checkpoints): each kept checkpoint
        finds its whole replay."""
        self._raise_failed()
        oldest = min(kept_rows, default=latest_rows)
        for s in range(self.num_seeds):
            for start, end, path in list_files(self.seed_dir(s)):
                partial = end - start < self.chunk_rows or end % self.chunk_rows
                if end <= oldest - self.rows:
                    path.unlink()
                elif partial and end <= latest_rows and end not in kept_rows:
                    path.unlink()

    # -- reading -----------------------------------------------------------------------------
    def restore(self, buffer: replay.ReplayState, rows_added: int) -> replay.ReplayState:
        """`buffer` (empty, [S, T, E, ...]) with the live rows of a checkpoint at `rows_added`."""
        lo = max(0, rows_added - self.rows)
        for s in range(self.num_seeds):
            files = [f for f in list_files(self.seed_dir(s)) if f[1] <= rows_added]
            cursor = lo
            while cursor < rows_added:
                covering = [f for f in files if f[0] <= cursor < f[1]]
                if not covering:
                    raise MissingReplayError(
                        f"replay rows from {cursor} of seed {s} are missing in "
                        f"{self.seed_dir(s)} (need rows {lo}..{rows_added - 1} for the "
                        "checkpoint); resume with replay.disk=False to refill the replay (the "
                        "agent's state kept), or delete the checkpoints to start over"
                    )
                start, end, path = max(covering, key=lambda f: f[1])
                try:
                    with np.load(path) as z:
                        data = {f: z[f][cursor - start :] for f in FIELDS}
                except (OSError, ValueError, KeyError, zipfile.BadZipFile, zlib.error) as e:
                    raise MissingReplayError(
                        f"replay file {path} cannot be read ({type(e).__name__}: {e}); it holds "
                        f"rows {start}..{end - 1} of seed {s}, which the checkpoint needs; "
                        "resume with replay.disk=False to refill the replay (the agent's state "
                        "kept), or delete the checkpoints to start over"
                    ) from None
                buffer = self._put(buffer, s, cursor, data)
                cursor = end
        return buffer

    def _put(self, buffer, seed: int, first: int, data: dict) -> replay.ReplayState:
        """Put rows first.. of `data` into ring rows, in pieces of one chunk (one program)."""
        n = len(data["frames"])
        for lo in range(0, n, self.chunk_rows):
            piece = {f: v[lo : lo + self.chunk_rows] for f, v in data.items()}
            k = len(piece["frames"])
            idx = np.full(self.chunk_rows, self.rows, np.int32)  # out of range: dropped
            idx[:k] = (first + lo + np.arange(k)) % self.rows
            pad = {
                f: np.concatenate([v, np.zeros((self.chunk_rows - k, *v.shape[1:]), v.dtype)])
                for f, v in piece.items()
            }
            buffer = _put_rows(buffer, seed, idx, pad)
        return buffer

    def close(self) -> None:
        try:
            self.flush()
        finally:
            self._executor.shutdown(wait=True)


def chunk_rows_for(chunk_entries: int, num_envs: int, rows: int) -> int:
    return max(1, min(math.ceil(chunk_entries / num_envs), rows))
