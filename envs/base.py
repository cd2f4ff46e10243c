"""The batched environment: physics + render pool + distractions + masks + frame stack.

`Env` glues the pieces of `envs/` into the interface the trainer uses (docs/design.md):
- physics (`envs/physics.py`, MJX or CPU MuJoCo) steps S x E envs through one agent step: CPU
  MuJoCo on the env thread below, MJX dispatched by the caller;
- a background thread (one-thread executor) steps CPU physics, fetches qpos to the host, renders
  RGB + pixel labels in the render pool (`envs/render_pool.py`), uploads them and dispatches one
  jitted function that composites the distraction background (`envs/distractions.py`), builds
  the mask variant (`envs/masks.py`) and rolls the frame stack; `step_async` returns at once, so
  the caller can dispatch accelerator work meanwhile;
- episodes: auto-reset with dm_env semantics, per env. Episode starts are drawn on the host (CPU
  MuJoCo, the task's `init_episode`: dm_control's law for DMC tasks, `envs/dmc.py`) from a numpy
  RandomState seeded by the key given to `reset`; both physics backends start from these
  qpos/qvel. Tasks with `success_ends_episode` (the kitchen) end an env's episode on the step its
  reward is 1 (success 1, discount 0), reading that reward on the host with the qpos the
  renderers need anyway.

State ownership: `EnvState` holds the physics state, the frame stack, the jax key and, as host
numpy leaves, the per-env step counters and `last` flags (so auto-reset needs no device sync).
The per-env distraction draws (colours, camera, background frame) and the host RNG live in the
Env object and advance with every step: an Env is stepped along one trajectory, not branched.
`host_state()` / `set_host_state()` read and restore them (numpy arrays and python numbers), so
a checkpointed run continues exactly.

Devices: with `sharding` (a NamedSharding of the seeds axis, `dear_jax/devices.py`), every host ->
device upload (frames, labels, rewards, flags, episode starts) lands split over the devices by
seed and the device programs keep it so: the one render pool feeds every device, and no array is
gathered onto one device. Without it, arrays go to the default device, uncommitted.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import time
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.sharding import PartitionSpec as P

from envs import distractions, dmc, masks
from envs.dmc import DmcTask
from envs.physics import SolverSettings, make_physics, resolve_backend, upload
from envs.render import RenderSettings
from envs.render_pool import RenderPool

MASK_KINDS = ("true", "noisy", "approximate")


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Static facts of a batched env (recorded in run summaries)."""

    name: str
    action_dim: int
    action_repeat: int
    episode_steps: int  # agent steps per episode after the first timestep
    frame_shape: tuple[int, int, int] = (84, 84, 3)
    frame_stack: int = 3
    has_success: bool = False
    floor_alpha: float = 1.0
    num_seeds: int = 1
    envs_per_seed: int = 1
    backend: str = "cpu"
    distraction: str = "none"
    distraction_types: tuple[str, ...] = ()  # of distractions.DISTRACTION_TYPES; () without
    backgrounds: str = "none"  # "DAVIS-2017 (<folder>)", "built-in procedural videos", "none"
    dynamic: bool = False
    mask: str = "true"
    physics_steps_per_agent_step: int = 1
    render_gpus: str = "auto"  # the GPUs its render workers draw on (RenderSettings.gpus)


@flax.struct.dataclass
class TimeStep:
    obs: jax.Array  # uint8 [S,E,H,W,3*stack], oldest frame first
    frame: jax.Array  # uint8 [S,E,H,W,3], newest composited frame
    mask: jax.Array  # uint8 [S,E,H,W] in {0,1}, chosen variant
    true_mask: jax.Array  # uint8 [S,E,H,W] in {0,1}
    reward: jax.Array  # f32 [S,E], summed over the action repeat; 0 on a first step
    discount: jax.Array  # f32 [S,E]
    first: jax.Array  # bool [S,E]
    last: jax.Array  # bool [S,E]
    success: jax.Array  # f32 [S,E]


@flax.struct.dataclass
class EnvState:
    physics: Any  # mjx.Data batched [S,E] (device) or physics.CpuState (host)
    stack: jax.Array  # uint8 [S,E,H,W,3*stack]
    key: jax.Array  # PRNG key for the mask noise
    step: np.ndarray  # host int64 [S,E]: agent steps since the episode's first timestep
    last: np.ndarray  # host bool [S,E]: the latest timestep ended its episode


def _post(
    rgb,
    labels,
    video,
    video_frame,
    reward,
    first,
    last,
    success,
    videos,
    stack,
    key,
    *,
    floor_alpha,
    mask_kind,
    drop_prob,
    composite,
    frame_stack,
):
    """Device half of a step, one program (jitted): each env's background frame (`videos`
    [V,T,H,W,3] at [video, video_frame]), composite, masks, frame stack, TimeStep fields.
    Returns (stack, TimeStep, the key's next state)."""
    key, mask_key = jax.random.split(key)
    if composite:
        frame = distractions.composite(rgb, labels, videos[video, video_frame], floor_alpha)
    else:
        frame = rgb
    true_mask = masks.agent_mask(labels)
    mask = masks.make_mask(labels, mask_key, mask_kind, drop_prob)
    rolled = jnp.concatenate([stack[..., 3:], frame], axis=-1)
    fresh = jnp.concatenate([frame] * frame_stack, axis=-1)
    obs = jnp.where(first[..., None, None, None], fresh, rolled)
    reward = jnp.where(first, 0.0, reward).astype(jnp.float32)
    ts = TimeStep(
        obs=obs,
        frame=frame,
        mask=mask,
        true_mask=true_mask,
        reward=reward,
        # Reaching a goal is a true terminal (no bootstrap); time limits are not.
        discount=jnp.where(success, 0.0, 1.0).astype(jnp.float32),
        first=first,
        last=last,
        success=success.astype(jnp.float32),
    )
    return obs, ts, key


class Env:
    """S x E envs of one task; see docs/design.md for the interface.

    task: a `DmcTask` (envs/dmc.py) or a `KitchenTask` (envs/kitchen.py); both provide the
    models, the reward, the control mapping, the episode start and the render facts. Tasks with
    `success_ends_episode` end an episode on the step their reward is 1 (success 1, discount 0).
    `video_seed` draws the built-in background videos (without `background_dir`; None: `seed`),
    so that envs of one run with seeds of their own (hosts, evaluation processes) share them.
    `label_envs`: where the render settings draw labels, only the first `label_envs` envs of
    each seed get them (the others' are all LABEL_BACKGROUND, as are their masks), unless
    backgrounds are composited, which read every env's (None: every env's; an evaluation's
    videos show env 0's true mask).
    """

    def __init__(
        self,
        task: DmcTask,
        *,
        num_seeds: int = 1,
        envs_per_seed: int = 1,
        backend: str = "auto",
        distraction: str = "none",
        distraction_types: str | tuple = distractions.DISTRACTION_TYPES,
        dynamic: bool = False,
        background_dir=None,
        split: str = "train",
        mask: str = "true",
        mask_drop_prob: float = 0.8,
        render: RenderSettings | None = None,
        seed: int = 0,
        video_seed: int | None = None,
        action_repeat: int = 2,
        solver: SolverSettings | None = None,
        episode_frames: int | None = None,
        sharding: jax.sharding.NamedSharding | None = None,
        physics_threads: int = 1,
        label_envs: int | None = None,
    ):
        render = render or RenderSettings()
        solver = solver or SolverSettings()
        if mask not in MASK_KINDS:
            raise ValueError(f"unknown mask {mask!r}; valid: {', '.join(MASK_KINDS)}")
        distractions.check_difficulty(distraction)
        types = distractions.parse_types(distraction_types) if distraction != "none" else ()
        with_videos = "background" in types
        if with_videos and not render.labels:  # compositing reads the labels
            render = dataclasses.replace(render, labels=True)
        if label_envs is not None and label_envs < 0:
            raise ValueError(f"label_envs must be >= 0 (None: every env), got {label_envs}")
        self._label_rows = None  # every sample's labels drawn, where render.labels
        if label_envs is not None and not with_videos and render.labels:
            if label_envs == 0:
                render = dataclasses.replace(render, labels=False)
            elif label_envs < envs_per_seed:
                self._label_rows = np.tile(np.arange(envs_per_seed) < label_envs, num_seeds)
        if not with_videos:
            backgrounds = "none"
        elif background_dir:
            backgrounds = f"DAVIS-2017 ({background_dir})"
        else:
            backgrounds = "built-in procedural videos"
        if num_seeds < 1 or envs_per_seed < 1 or action_repeat < 1:
            raise ValueError(
                f"num_seeds, envs_per_seed and action_repeat must be >= 1, got "
                f"{num_seeds}, {envs_per_seed}, {action_repeat}"
            )
        self.task = task
        self.shape = (num_seeds, envs_per_seed)
        self.batch = num_seeds * envs_per_seed
        self.sharding = sharding
        self._model = task.physics_model()
        self._data = mujoco.MjData(self._model)
        n_sub = task.n_sub_steps(self._model)
        # episode_frames shortens (or lengthens) episodes, e.g. for smoke runs and tests.
        frames = int(episode_frames) if episode_frames else task.frames_per_episode(self._model)
        if frames % action_repeat:
            raise ValueError(f"{frames} frames per episode not divisible by {action_repeat}")
        backend = resolve_backend(backend)
        self.physics = make_physics(
            backend,
            self._model,
            task.make_reward(self._model),
            n_sub_steps=n_sub,
            action_repeat=action_repeat,
            solver=solver,
            control=task.make_control(self._model),
            sharding=sharding,
            threads=physics_threads,
        )
        h, w = render.height, render.width
        self.spec = EnvSpec(
            name=task.name,
            action_dim=self._model.nu,
            action_repeat=action_repeat,
            episode_steps=frames // action_repeat,
            frame_shape=(h, w, 3),
            has_success=task.success_ends_episode,
            floor_alpha=task.floor_alpha,
            num_seeds=num_seeds,
            envs_per_seed=envs_per_seed,
            backend=backend,
            distraction=distraction,
            distraction_types=types,
            backgrounds=backgrounds,
            dynamic=dynamic,
            mask=mask,
            physics_steps_per_agent_step=n_sub * action_repeat,
            render_gpus=render.gpus,
        )
        self.render_settings = render

        render_model = task.render_model(render.mesh_faces)
        if not with_videos:
            videos = np.zeros((1, 1, h, w, 3), np.uint8)
            num_videos, num_frames, lengths = 0, 1, None
        else:
            videos, lengths = distractions.load_backgrounds(
                background_dir,
                split,
                distractions.difficulty_videos(distraction),
                size=h,
                seed=seed if video_seed is None else video_seed,
                with_lengths=True,
            )
            num_videos, num_frames = videos.shape[:2]
        # Every device holds all videos (and the mask noise's key): each looks up its own seeds'
        # background frames.
        everywhere = None if sharding is None else jax.sharding.NamedSharding(sharding.mesh, P())
        self._everywhere = everywhere
        self._backgrounds = (
            jnp.asarray(videos) if sharding is None else jax.device_put(videos, everywhere)
        )
        self._distractor = distractions.Distractor(
            render_model,
            task.camera,
            distraction,
            dynamic=dynamic,
            batch=self.batch,
            num_videos=num_videos,
            num_frames=num_frames,
            lengths=lengths,
            seed=seed,
            color="color" in types,
            camera_motion="camera" in types,
            background=with_videos,
        )
        self._post = jax.jit(
            functools.partial(
                _post,
                floor_alpha=task.floor_alpha,
                mask_kind=mask,
                drop_prob=mask_drop_prob,
                composite=with_videos,
                frame_stack=self.spec.frame_stack,
            ),
            **({} if sharding is None else {"out_shardings": (sharding, sharding, everywhere)}),
        )
        self._rng = np.random.RandomState(seed)
        self._host_s = dict.fromkeys(("action", "physics", "draw", "post"), 0.0)
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="env")
        self._pool = RenderPool(
            task.render_factory(render.mesh_faces),
            camera=task.camera,
            agent_geom_ids=task.agent_geom_ids(render_model),
            floor_geom_ids=task.floor_geom_ids(render_model),
            settings=render,
            batch=self.batch,
        )

    def _upload(self, x) -> jax.Array:
        return upload(x, self.sharding)

    # -- episode starts (host) --------------------------------------------------------------
    def _initial_states(self, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """qpos [S,E,nq], qvel [S,E,nv]: fresh episode starts where `which`, qpos0 elsewhere."""
        m, d = self._model, self._data
        qpos = np.tile(m.qpos0, self.shape + (1,))
        qvel = np.zeros(self.shape + (m.nv,))
        for s, e in zip(*np.nonzero(which), strict=True):
            dmc.episode_start(self.task, m, d, self._rng)
            qpos[s, e], qvel[s, e] = d.qpos, d.qvel
        return qpos, qvel

    # -- public API ---------------------------------------------------------------------------
    def reset(self, key: jax.Array) -> tuple[EnvState, TimeStep]:
        key, host_key = jax.random.split(key)
        self._rng = np.random.RandomState(int(jax.random.randint(host_key, (), 0, 2**31 - 1)))
        everyone = np.ones(self.shape, bool)
        phys = self.physics.init(*self._initial_states(everyone))
        self._distractor.reset(None)
        step = np.zeros(self.shape, np.int64)
        stack = self._upload(
            np.zeros(
                self.shape + self.spec.frame_shape[:2] + (3 * self.spec.frame_stack,), np.uint8
            )
        )
        return self._finish(
            phys,
            np.zeros(self.shape, np.float32),
            first=everyone,
            step=step,
            stack=stack,
            key=key,
            perturb=self._distractor.perturb(),
            bg_index=self._distractor.background_index(),
        )

    def step_async(self, state: EnvState, action: jax.Array) -> concurrent.futures.Future:
        """Step the physics and render on the env thread (MJX physics: dispatched here, on the
        accelerator); returns a Future at once, so the caller can dispatch device work meanwhile.

        CPU physics reads `action` on the env thread: the caller is never held up waiting for it.
        """
        reset = np.asarray(state.last, bool)
        starts = self._initial_states(reset) if reset.any() else None  # host RNG, in step order
        step = np.where(reset, 0, state.step + 1)
        # Snapshot the host distraction draws now: the next step_async mutates them. Dynamic
        # distractions move once per frame, as the Distracting Control Suite's (under the
        # action repeat): action_repeat moves per step.
        for _ in range(self.spec.action_repeat):
            self._distractor.step()
        if reset.any():
            self._distractor.reset(reset.reshape(-1))
        finish = functools.partial(
            self._finish,
            first=reset,
            step=step,
            stack=state.stack,
            key=state.key,
            perturb=self._distractor.perturb(),
            bg_index=self._distractor.background_index(),
        )
        advance = functools.partial(self._advance, state.physics, action, reset, starts)
        if self.physics.on_host:
            return self._executor.submit(lambda: finish(*advance()))
        return self._executor.submit(finish, *advance())

    def _advance(self, phys, action, reset, starts):
        """(physics state, reward [S,E]) one agent step on; envs in `reset` start anew."""
        t0 = t1 = time.perf_counter()
        if reset.all():  # no env reads the actions
            phys, reward = self.physics.init(*starts), np.zeros(self.shape, np.float32)
        else:
            if self.physics.on_host:  # the policy's actions, computed after the queued updates
                action = np.asarray(action)
                t1 = time.perf_counter()
            phys, reward = self.physics.step(phys, action)
            if starts is not None:
                phys = self.physics.where(reset, self.physics.init(*starts), phys)
        self._host_s["action"] += t1 - t0
        self._host_s["physics"] += time.perf_counter() - t1
        return phys, reward

    def take_host_seconds(self) -> dict[str, float]:
        """Seconds the steps since the last call spent, by stage, on the host: "action" (CPU
        physics: the wait for the actions, which the accelerator computes after the updates
        queued before them), "physics" (CPU physics; MJX: its dispatch and the wait for the states),
        "draw" (the render pool's frames and labels) and "post" (the frames' upload and their
        device program's dispatch); then starts counting again. Call it with no step in flight."""
        taken, self._host_s = self._host_s, dict.fromkeys(self._host_s, 0.0)
        return taken

    def step(self, state: EnvState, action: jax.Array) -> tuple[EnvState, TimeStep]:
        return self.step_async(state, action).result()

    def host_state(self) -> dict:
        """Host RNG and distraction state (copies): with an EnvState, all a resume needs."""
        _, keys, pos, has_gauss, cached = self._rng.get_state()
        rng = {"keys": keys.copy(), "pos": pos, "has_gauss": has_gauss, "cached": cached}
        return {"episode_rng": rng, "distractor": self._distractor.get_state()}

    def set_host_state(self, state: dict) -> None:
        r = state["episode_rng"]
        self._rng = np.random.RandomState()
        keys = np.asarray(r["keys"], np.uint32)
        self._rng.set_state(
            ("MT19937", keys, int(r["pos"]), int(r["has_gauss"]), float(r["cached"]))
        )
        self._distractor.set_state(state["distractor"])

    def _finish(self, phys, reward, *, first, step, stack, key, perturb, bg_index):
        """The step's state and timestep from its physics state and reward: frames drawn, then
        uploaded with the step's other host arrays."""
        t0 = time.perf_counter()
        qpos = np.asarray(self.physics.qpos(phys)).reshape(self.batch, -1)
        t1 = time.perf_counter()
        rgb, labels = self._pool.render(qpos, perturb=perturb, label_rows=self._label_rows)
        t2 = time.perf_counter()
        h, w, _ = self.spec.frame_shape
        video, video_frame = bg_index
        last = step >= self.spec.episode_steps
        success = np.zeros(self.shape, bool)
        if self.task.success_ends_episode:
            # The reward is 1 exactly while the goal is reached; the first such step ends it.
            success = (np.asarray(reward).reshape(self.shape) > 0) & ~first
            last = last | success
            reward = success.astype(np.float32)
        # The step's host arrays are the arguments of one program (sharded: placed by one
        # transfer call first): on the env thread every dispatch is a wait beside the training's.
        per_env = (
            np.reshape(rgb, self.shape + (h, w, 3)),
            np.reshape(labels, self.shape + (h, w)),
            np.reshape(video, self.shape),
            np.reshape(video_frame, self.shape),
            reward,
            first,
            last,
            success,
        )
        if self.sharding is not None:  # the key where `_post` leaves it: one compile
            per_env, key = jax.device_put((per_env, key), (self.sharding, self._everywhere))
        stack, ts, key = self._post(*per_env, self._backgrounds, stack, key)
        self._host_s["physics"] += t1 - t0
        self._host_s["draw"] += t2 - t1
        self._host_s["post"] += time.perf_counter() - t2
        state = EnvState(physics=phys, stack=stack, key=key, step=step, last=last)
        return state, ts

    def close(self) -> None:
        self._executor.shutdown(wait=True)
        self._pool.close()
        if hasattr(self.physics, "close"):  # CPU MuJoCo's threads
            self.physics.close()

    def __enter__(self) -> Env:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
