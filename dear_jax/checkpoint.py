"""Checkpoints of a run: orbax `CheckpointManager`, atomic, last k kept, guarded by a fingerprint.

Each checkpoint step holds two orbax items:
  state  the pytree of arrays (agent states vmapped over seeds, RNG key data, env states...);
  meta   json: {"fingerprint": the config fields a resume must match, "extra": host values}.
`extra` may hold numpy arrays (host RNG states, CPU physics): they are stored in the json as
base64 bytes with their dtype and shape, so they come back bit for bit, float64 included.

Atomicity is orbax's: a step is written into `<step>.orbax-checkpoint-tmp*` and renamed to
`<step>` only after every file is on disk, so a process killed mid-save leaves the earlier steps
untouched; the stale temporary folder is ignored by `latest_step` and deleted the next time a
`Checkpointer` opens the folder.

Leaves come back as jax arrays placed like the template's (numpy leaves: on the default device);
without jax_enable_x64, 64-bit numpy leaves come back as 32-bit, as jax.numpy would make them.
Zero-size leaves (MJX data of a model without tendons, mocap bodies...) are not stored (orbax
refuses them); they come back as the template's.

Several processes (`jax.distributed`): every process calls `save` and `restore` with the same
global arrays, and orbax writes and reads each process's shards. The `meta` item is written by
process 0 only, so each process also keeps its own `extra` (its envs' host RNG states, its lanes'
log sums) in `<directory>_process_<i>/<step>.json`, written before the step is committed and
deleted with it; `read_meta` then returns the calling process's `extra`.

Typed JAX PRNG keys (`jax.random.key`) are stored as their uint32 key data and re-wrapped on
restore with the template's key implementation, so callers may pass either form.
"""

from __future__ import annotations

import base64
import json
import logging
import os
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

log = logging.getLogger(__name__)

_STATE, _META = "state", "meta"


def _read_failure(e: BaseException) -> str | None:
    """Where orbax's restore failed reading stored bytes, the reason (the first line of the
    ValueError it was raised from, such as TensorStore's OUT_OF_RANGE; else its own); else None."""
    chain = []
    while e is not None and e not in chain:
        chain.append(e)
        e = e.__cause__
    for x in chain:
        if isinstance(x, ValueError):
            return str(x).splitlines()[0][:400]
    if any("error while reading" in str(x) for x in chain):
        return str(chain[-1]).splitlines()[0][:400]
    return None


def _skip_unrequested_item(record: logging.LogRecord) -> bool:
    # Reading only the json item makes orbax warn that the array item was not restored.
    return "could not be restored" not in record.getMessage()


class IncompatibleCheckpointError(ValueError):
    """The checkpoint was written by a run whose fingerprint (config) differs from this one."""


class UnreadableCheckpointError(ValueError):
    """A checkpoint whose metadata matches the run but whose arrays cannot be read: its files
    were damaged after it was written (orbax writes them atomically)."""


_NDARRAY = "__ndarray__"


def _encode_arrays(value: Any) -> Any:
    """numpy arrays (and numpy scalars) inside dicts / lists -> json objects holding their bytes."""
    if isinstance(value, (np.ndarray, np.generic)):
        arr = np.asarray(value)
        data = base64.b64encode(arr.tobytes()).decode("ascii")
        return {_NDARRAY: arr.dtype.str, "shape": list(arr.shape), "data": data}
    if isinstance(value, Mapping):
        return {k: _encode_arrays(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode_arrays(v) for v in value]
    return value


def _decode_arrays(value: Any) -> Any:
    if isinstance(value, dict):
        if _NDARRAY in value:
            raw = base64.b64decode(value["data"])
            return np.frombuffer(raw, np.dtype(value[_NDARRAY])).reshape(value["shape"]).copy()
        return {k: _decode_arrays(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode_arrays(v) for v in value]
    return value


def _jsonable(value: Any, what: str) -> Any:
    """`value` as json would give it back (tuples -> lists), so saved and current compare equal."""
    try:
        return json.loads(json.dumps(_encode_arrays(value)))
    except (TypeError, ValueError) as e:
        raise TypeError(
            f"{what} must be json-serialisable (numbers, strings, lists, dicts): {e}"
        ) from e


def _is_key(x: Any) -> bool:
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def _to_storable(x: Any) -> Any:
    if _is_key(x):
        x = jax.random.key_data(x)
    if not isinstance(x, jax.Array):
        x = np.asarray(x)  # python / numpy scalars become 0-d arrays, so every leaf is an array
    return None if x.size == 0 else x


def _is_none(x: Any) -> bool:
    return x is None


def _with_empty_leaves(template: Any, restored: Any) -> Any:
    """`restored` (zero-size leaves stored as None) with the template's zero-size leaves put back."""
    t_leaves, treedef = jax.tree.flatten(template, is_leaf=_is_none)
    r_leaves = jax.tree.leaves(restored, is_leaf=_is_none)
    leaves = [
        t if t is None or np.size(t) == 0 else r for t, r in zip(t_leaves, r_leaves, strict=True)
    ]
    return treedef.unflatten(leaves)


def _abstract(x: Any) -> jax.ShapeDtypeStruct | None:
    """What orbax should restore a template leaf as: same shape and dtype, same device(s)."""
    if _is_key(x):
        x = jax.random.key_data(x)
    if np.size(x) == 0:
        return None
    if isinstance(x, jax.Array):
        sharding = x.sharding
    else:
        x = np.asarray(x)
        sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)


def _key_name(entry) -> str:
    for attr in ("key", "name", "idx"):  # DictKey, GetAttrKey, SequenceKey / FlattenedIndexKey
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def _named_leaves(tree: Any) -> list[tuple[str, Any]]:
    """Leaves with orbax's names ("agent.opt_state.0.mu.encoder.kernel")."""
    flat, _ = jax.tree_util.tree_flatten_with_path(tree)
    return [(".".join(_key_name(e) for e in path), leaf) for path, leaf in flat]


def fingerprint_diff(saved: Mapping, now: Mapping, added: Mapping | None = None) -> list[str]:
    """Lines "key: saved=..., now=..." for every key whose value differs (or is on one side).
    added: keys newer than some checkpoints, with the value that matches their absence."""
    missing = "<absent>"
    added = added or {}
    lines = []
    for key in sorted(set(saved) | set(now), key=str):
        a, b = saved.get(key, missing), now.get(key, missing)
        if a is missing and key in added and b == added[key]:
            continue
        if a != b:
            older = a is missing and key in added
            hint = (
                f" (a field newer than the checkpoint: {added[key]!r} resumes it)" if older else ""
            )
            lines.append(f"{key}: saved={a!r}, now={b!r}{hint}")
    return lines


class Checkpointer:
    """Save / restore (state pytree, json extra) per step in `directory`, keeping the last `keep`.

    `save` blocks until the step is committed unless `asynchronous=True`; then it returns once the
    arrays are copied off the accelerator and the files are written in the background (`wait()`
    blocks; the next save, restore and close wait first).
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        *,
        fingerprint: dict,
        added_fields: Mapping | None = None,
        keep: int = 3,
        asynchronous: bool = False,
    ):
        if keep < 1:
            raise ValueError(f"keep must be >= 1, got {keep}")
        self.directory = os.path.abspath(os.fspath(directory))
        self.fingerprint = _jsonable(dict(fingerprint), "fingerprint")
        # Fields newer than some checkpoints: the value each has in a checkpoint without it.
        self.added_fields = dict(added_fields or {})
        options = ocp.CheckpointManagerOptions(
            max_to_keep=keep,
            create=True,
            cleanup_tmp_directories=True,  # a save killed half way left one behind
            enable_async_checkpointing=asynchronous,
        )
        # Handlers given up front (not registered by the first save) so that a new process can
        # read the stored array metadata before restoring (`_check_template`).
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=options,
            item_handlers={
                _STATE: ocp.StandardCheckpointHandler(),
                _META: ocp.JsonCheckpointHandler(),
            },
        )
        self._own = None  # this process's extras folder, with several processes
        if jax.process_count() > 1:
            self._own = f"{self.directory}_process_{jax.process_index()}"
            os.makedirs(self._own, exist_ok=True)
        # orbax deletes a killed save's temporary folder in a background thread and waits for it
        # only before its next save; wait now, so the folder is clean once the manager is open.
        getattr(self._manager, "_maybe_await_cleanup_tmp_directory", lambda: None)()

    def all_steps(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def wait(self) -> None:
        """Block until an asynchronous save has been committed."""
        self._manager.wait_until_finished()

    def save(self, step: int, state: Any, *, extra: dict | None = None) -> bool:
        """Write `state` (pytree of arrays) and `extra` (json) as checkpoint `step`.

        Returns False (and writes nothing) if `step` is already saved: the loop may ask for the
        final frame's checkpoint right after a periodic one at the same frame.
        """
        step = int(step)
        self.wait()
        if step in self._manager.all_steps():
            log.info("checkpoint %d already exists in %s; not rewritten", step, self.directory)
            return False
        meta = {"fingerprint": self.fingerprint, "extra": _jsonable(extra or {}, "extra")}
        if self._own is not None:
            path = os.path.join(self._own, f"{step}.json")
            with open(path + ".tmp", "w") as f:
                json.dump(meta["extra"], f)
            os.replace(path + ".tmp", path)
        saved = self._manager.save(
            step,
            args=ocp.args.Composite(
                **{
                    _STATE: ocp.args.StandardSave(jax.tree.map(_to_storable, state)),
                    _META: ocp.args.JsonSave(meta),
                }
            ),
        )
        if self._own is not None:
            self.wait()
            kept = {f"{s}.json" for s in self._manager.all_steps()}
            for name in set(os.listdir(self._own)) - kept:
                os.remove(os.path.join(self._own, name))
        return bool(saved)

    def read_meta(self, step: int | None = None) -> tuple[int, dict, dict]:
        """(step, stored fingerprint, extra) without reading any array."""
        step = self._resolve(step)
        absl_log = logging.getLogger("absl")
        absl_log.addFilter(_skip_unrequested_item)
        try:
            meta = self._manager.restore(
                step, args=ocp.args.Composite(**{_META: ocp.args.JsonRestore()})
            )[_META]
            extra, fingerprint = meta["extra"], meta["fingerprint"]
        except (ValueError, KeyError, TypeError, OSError) as e:  # json's errors are ValueErrors
            self._raise_unreadable(step, f"its metadata: {type(e).__name__}: {e}", e)
        finally:
            absl_log.removeFilter(_skip_unrequested_item)
        if self._own is not None:
            path = os.path.join(self._own, f"{step}.json")
            if not os.path.exists(path):
                raise IncompatibleCheckpointError(
                    f"checkpoint {step} in {self.directory} holds no host state of process "
                    f"{jax.process_index()} ({path}): it was written by fewer processes; resume "
                    "with as many processes as wrote it"
                )
            try:
                with open(path) as f:
                    extra = json.load(f)
            except (ValueError, OSError) as e:  # json's errors are ValueErrors
                self._raise_unreadable(step, f"{path}: {type(e).__name__}: {e}", e)
        return step, fingerprint, _decode_arrays(extra)

    def check_fingerprint(self, saved: Mapping, step: int) -> None:
        """Raise IncompatibleCheckpointError, naming every differing field, unless `saved` matches."""
        diff = fingerprint_diff(saved, self.fingerprint, self.added_fields)
        if diff:
            raise IncompatibleCheckpointError(
                f"checkpoint {step} in {self.directory} was written by a different "
                "configuration:\n  "
                + "\n  ".join(diff)
                + "\nResume with the original config, or start this one in a new --workdir."
                + (
                    "\n(env.backend's default was 'auto' until 2026-11-23, now 'cpu': this run "
                    f"resumes with --config.env.backend={saved.get('env.backend', 'auto')})"
                    if any(d.startswith("env.backend:") for d in diff)
                    else ""
                )
            )

    def restore(self, template: Any, step: int | None = None) -> tuple[int, Any, dict]:
        """(step, state shaped like `template`, extra) of `step` (default: the latest).

        Raises IncompatibleCheckpointError before reading arrays if the stored fingerprint differs,
        and ValueError if the stored arrays do not match the template's structure/shapes/dtypes.
        """
        self.wait()
        step, saved_fp, extra = self.read_meta(step)
        self.check_fingerprint(saved_fp, step)
        abstract = jax.tree.map(_abstract, template)
        self._check_template(step, abstract)
        try:
            restored = self._manager.restore(
                step,
                args=ocp.args.Composite(**{_STATE: ocp.args.StandardRestore(abstract)}),
            )[_STATE]
        except Exception as e:  # names, shapes and dtypes matched: the bytes are what failed
            self._raise_if_unreadable(step, e)
            raise
        restored = _with_empty_leaves(template, restored)
        restored = jax.tree.map(
            lambda t, r: (
                jax.random.wrap_key_data(r, impl=jax.random.key_impl(t)) if _is_key(t) else r
            ),
            template,
            restored,
        )
        return step, restored, extra

    def read_arrays(self, step: int | None = None) -> dict:
        """The stored arrays of `step` (default: the latest) as nested dicts of numpy arrays,
        without a template (to inspect or compare checkpoints)."""
        self.wait()
        step = self._resolve(step)
        # Onto one device, whatever devices the run that saved them had split them over.
        stored = self._manager.item_metadata(step)[_STATE]
        one = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        abstract = jax.tree.map(
            lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=one),
            getattr(stored, "tree", stored),
            is_leaf=lambda m: hasattr(m, "shape") and hasattr(m, "dtype"),
        )
        restored = self._manager.restore(
            step, args=ocp.args.Composite(**{_STATE: ocp.args.StandardRestore(abstract)})
        )[_STATE]
        return jax.tree.map(np.asarray, restored)

    def _raise_if_unreadable(self, step: int, e: Exception) -> None:
        """UnreadableCheckpointError for checkpoint `step` where `e` is orbax failing to read its
        bytes (the way on: the checkpoint before it); otherwise nothing (the caller re-raises)."""
        reason = _read_failure(e)
        if reason is None:
            return
        self._raise_unreadable(step, reason, e)

    def _raise_unreadable(self, step: int, reason: str, e: Exception) -> None:
        earlier = [s for s in self.all_steps() if s < step]
        way_on = (
            f"to resume from checkpoint {earlier[-1]} before it"
            if earlier
            else "to start over (it is the only one)"
        )
        raise UnreadableCheckpointError(
            f"checkpoint {step} in {self.directory} cannot be read (its files damaged since it "
            "was written, or a layout this code does not read) "
            f"({reason}). Move {os.path.join(self.directory, str(step))} out of "
            f"{self.directory} {way_on}, or start over in a new --workdir"
        ) from e

    def _resolve(self, step: int | None) -> int:
        steps = self.all_steps()
        if not steps:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        if step is None:
            return steps[-1]
        if int(step) not in steps:
            raise FileNotFoundError(
                f"no checkpoint {step} in {self.directory}; available steps: {steps}"
            )
        return int(step)

    def _check_template(self, step: int, abstract: Any) -> None:
        """Compare names, shapes and dtypes with the stored array metadata before reading.

        orbax would cast a different dtype silently (a changed dtype means a changed program), and
        its own shape and structure errors leave half-started reads behind.
        """
        try:
            stored_tree = self._manager.item_metadata(step)[_STATE]
        except Exception as e:
            self._raise_if_unreadable(step, e)
            raise
        stored = {
            m.name: m
            for m in jax.tree.leaves(getattr(stored_tree, "tree", stored_tree))
            if hasattr(m, "name") and hasattr(m, "shape")
        }
        if not stored:
            return  # no metadata to compare with: orbax checks what it can
        wanted = dict(_named_leaves(abstract))
        problems = [f"{n}: not in the template" for n in sorted(set(stored) - set(wanted))]
        problems += [f"{n}: not in the checkpoint" for n in sorted(set(wanted) - set(stored))]
        for name in sorted(set(stored) & set(wanted)):
            m, t = stored[name], wanted[name]
            if tuple(m.shape) != tuple(t.shape) or np.dtype(m.dtype) != np.dtype(t.dtype):
                problems.append(
                    f"{name}: saved {np.dtype(m.dtype)}{list(m.shape)}, "
                    f"template {np.dtype(t.dtype)}{list(t.shape)}"
                )
        if problems:
            shown = problems[:20] + (
                [f"... {len(problems) - 20} more"] if len(problems) > 20 else []
            )
            raise ValueError(
                f"checkpoint {step} in {self.directory} does not match the state template "
                "(a code change of the agent or replay layout?):\n  " + "\n  ".join(shown)
            )

    def close(self) -> None:
        self._manager.wait_until_finished()
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
