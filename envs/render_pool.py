"""The render pool: worker processes turning batched MuJoCo states into frames and labels.

Each worker process has its own MjModel, MjData, EGL context and MuJoCo render context, held by
one `TileRenderer` (envs/render.py), and draws its share of a batch. Results return through one
shared-memory block; only the small inputs (qpos, perturbations) are pickled.
"""

from __future__ import annotations

import os
import threading
import traceback
from collections.abc import Callable
from multiprocessing import connection, resource_tracker, shared_memory
from typing import Any

import mujoco
import numpy as np

from envs import forkserver
from envs.render import CPU, PERTURB_KEYS, RenderSettings, TileRenderer, use_cpu_drawing

_WORKER_TIMEOUT_S = 600.0


def _attach_shm(name: str) -> shared_memory.SharedMemory:
    # The parent owns and unlinks the block; a worker that registered it with the resource
    # tracker would make the tracker unlink it (or warn about a leak) when the worker exits.
    register = resource_tracker.register
    resource_tracker.register = lambda *args, **kwargs: None
    try:
        return shared_memory.SharedMemory(name=name)
    finally:
        resource_tracker.register = register


def _worker_main(conn, model_fn, init_kwargs, gpu: int | str | None) -> None:
    # A stop signal sent to the whole process group is the parent's to handle: it finishes its
    # step, checkpoints and then closes the pool. A worker also ends when the parent's end of
    # the pipe closes (EOF below), so it never outlives the parent.
    forkserver.ignore_stop_signals()
    renderer = None
    shm = None
    try:
        if gpu == CPU:
            use_cpu_drawing()
        elif gpu is not None:  # read by MuJoCo's EGL backend when it makes the context
            os.environ["MUJOCO_EGL_DEVICE_ID"] = str(gpu)
        renderer = TileRenderer(model_fn(), **init_kwargs)
        conn.send(("ok", None))
    except BaseException:  # noqa: BLE001 - any failure must reach the parent
        conn.send(("error", traceback.format_exc()))
        return
    h, w = init_kwargs["settings"].height, init_kwargs["settings"].width
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            break
        kind = msg[0]
        try:
            if kind == "close":
                break
            if kind == "info":
                egl_device = os.environ.get("MUJOCO_EGL_DEVICE_ID", "")
                conn.send(("ok", {**renderer.gl_info(), "MUJOCO_EGL_DEVICE_ID": egl_device}))
            elif kind == "render":
                _, shm_name, capacity, lo, qpos, mocap_pos, mocap_quat, perturb, label_rows = msg
                if shm is None or shm.name != shm_name:
                    if shm is not None:
                        shm.close()
                    shm = _attach_shm(shm_name)
                rgb, labels = _views(shm, capacity, h, w)
                n = qpos.shape[0]
                renderer.render(
                    qpos,
                    rgb[lo : lo + n],
                    labels[lo : lo + n],
                    mocap_pos=mocap_pos,
                    mocap_quat=mocap_quat,
                    perturb=perturb,
                    label_rows=label_rows,
                )
                conn.send(("ok", None))
            else:
                conn.send(("error", f"unknown message {kind!r}"))
        except BaseException:  # noqa: BLE001
            conn.send(("error", traceback.format_exc()))
    if shm is not None:
        shm.close()
    renderer.close()


def _views(shm: shared_memory.SharedMemory, capacity: int, h: int, w: int):
    rgb = np.ndarray((capacity, h, w, 3), np.uint8, buffer=shm.buf)
    labels = np.ndarray((capacity, h, w), np.uint8, buffer=shm.buf, offset=capacity * h * w * 3)
    return rgb, labels


def _hint(error: str, workers: int) -> str:
    """What to do about a worker's known failures (empty if none applies)."""
    if "Offscreen framebuffer is not complete" not in error:
        return ""
    # Seen on an H100 (2026-11-24): the 5th and 6th training process on one GPU, each with
    # 8 workers for its training env and 8 for its evaluation env, could not make their
    # offscreen buffers while 4 others ran, with 26 GB of the GPU's memory still free.
    return (
        f"\nThe GPU's EGL driver gave this worker no offscreen buffer. This env has {workers} "
        "render workers, each with its own GL context; other processes on this GPU hold theirs. "
        "Lower env.render.num_workers (e.g. --config.env.render.num_workers=2), or run fewer "
        "training processes on this GPU (several seeds or a sweep in one run share one set)."
    )


class RenderPool:
    """Worker processes turning batched states into RGB frames and pixel labels.

    model_fn: picklable zero-argument callable returning a mujoco.MjModel (each worker calls it).
    camera: camera id or name. agent_geom_ids / floor_geom_ids: geom ids for the labels.
    batch: the samples of a usual `render` call, if known (`RenderSettings.resolved_workers`).
    """

    def __init__(
        self,
        model_fn: Callable[[], mujoco.MjModel],
        *,
        camera: int | str,
        agent_geom_ids,
        floor_geom_ids,
        settings: RenderSettings = RenderSettings(),
        batch: int | None = None,
    ):
        self.settings = settings
        self._lock = threading.Lock()
        self._shm: shared_memory.SharedMemory | None = None
        self._capacity = 0
        init_kwargs = dict(
            camera=camera,
            agent_geom_ids=[int(i) for i in agent_geom_ids],
            floor_geom_ids=[int(i) for i in floor_geom_ids],
            settings=settings,
        )
        # Not fork: the parent may hold JAX / CUDA threads that a fork would corrupt. The
        # process's fork server (multiprocessing's, started by the first pool or evaluation
        # process with its modules imported; importing them starts no JAX backend) forks each
        # worker: on a 2-core machine a later 1-worker walker env was made and reset in 1.0 s
        # instead of the 3.0-3.6 s of spawning an interpreter that imports them.
        ctx = forkserver.context("envs.render_pool", "envs.registry")
        self._conns: list[connection.Connection] = []
        self._procs = []
        for gpu in settings.worker_gpus(settings.resolved_workers(batch)):
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=_worker_main, args=(child, model_fn, init_kwargs, gpu), daemon=True
            )
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
        try:
            for i in range(len(self._conns)):
                self._receive(i)
        except BaseException:
            self.close()
            raise

    @property
    def num_workers(self) -> int:
        return len(self._conns)

    def _receive(self, i: int) -> Any:
        conn, proc = self._conns[i], self._procs[i]
        deadline = _WORKER_TIMEOUT_S
        while not conn.poll(1.0):
            deadline -= 1.0
            if not proc.is_alive():
                raise RuntimeError(f"render worker {i} died (exit code {proc.exitcode})")
            if deadline <= 0:
                raise TimeoutError(f"render worker {i} gave no answer in {_WORKER_TIMEOUT_S} s")
        status, payload = conn.recv()
        if status != "ok":
            raise RuntimeError(
                f"render worker {i} failed:\n{payload}{_hint(payload, len(self._procs))}"
            )
        return payload

    def _ensure_capacity(self, batch: int) -> None:
        if batch <= self._capacity:
            return
        h, w = self.settings.height, self.settings.width
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
        self._capacity = batch
        self._shm = shared_memory.SharedMemory(create=True, size=batch * h * w * 4)

    def gl_info(self) -> list[dict[str, str]]:
        """GL vendor / renderer / version strings of every worker's context, and the
        MUJOCO_EGL_DEVICE_ID it was made under ("" where unset)."""
        with self._lock:
            for conn in self._conns:
                conn.send(("info",))
            return [self._receive(i) for i in range(len(self._conns))]

    def render(
        self,
        qpos: np.ndarray,
        *,
        mocap_pos: np.ndarray | None = None,
        mocap_quat: np.ndarray | None = None,
        perturb: dict[str, np.ndarray] | None = None,
        label_rows: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """qpos [B,nq] -> (rgb uint8 [B,H,W,3], labels uint8 [B,H,W]). perturb: PERTURB_KEYS.
        label_rows: bool [B], the samples whose labels are drawn (None: all; `TileRenderer`)."""
        qpos = np.asarray(qpos, np.float64)
        if qpos.ndim != 2:
            raise ValueError(f"qpos must be [B, nq], got shape {qpos.shape}")
        perturb = {k: np.asarray(v) for k, v in (perturb or {}).items()}
        unknown = set(perturb) - set(PERTURB_KEYS)
        if unknown:
            raise ValueError(f"unknown perturbation keys {sorted(unknown)}; valid: {PERTURB_KEYS}")
        batch = qpos.shape[0]
        if label_rows is not None:
            label_rows = np.asarray(label_rows, bool)
            if label_rows.shape != (batch,):
                raise ValueError(f"label_rows must be [B] = [{batch}], got {label_rows.shape}")
        for name, arr in [("mocap_pos", mocap_pos), ("mocap_quat", mocap_quat), *perturb.items()]:
            if arr is not None and np.shape(arr)[0] != batch:
                raise ValueError(f"{name} has leading dim {np.shape(arr)[0]}, qpos has {batch}")
        h, w = self.settings.height, self.settings.width
        with self._lock:
            self._ensure_capacity(batch)
            bounds = np.linspace(0, batch, len(self._conns) + 1).round().astype(int)
            busy = []
            for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
                if hi <= lo:
                    continue
                part = slice(lo, hi)
                self._conns[i].send(
                    (
                        "render",
                        self._shm.name,
                        self._capacity,
                        int(lo),
                        qpos[part],
                        None if mocap_pos is None else np.asarray(mocap_pos)[part],
                        None if mocap_quat is None else np.asarray(mocap_quat)[part],
                        {k: v[part] for k, v in perturb.items()},
                        None if label_rows is None else label_rows[part],
                    )
                )
                busy.append(i)
            errors = []
            for i in busy:
                try:
                    self._receive(i)
                except RuntimeError as err:
                    errors.append(err)
            if errors:
                raise errors[0]
            rgb, labels = _views(self._shm, self._capacity, h, w)
            return rgb[:batch].copy(), labels[:batch].copy()

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close",))
            except (BrokenPipeError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()  # workers ignore SIGTERM
                proc.join(timeout=10)
        for conn in self._conns:
            conn.close()
        self._conns, self._procs = [], []
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    def __enter__(self) -> RenderPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_conns", None):
            self.close()
