"""Batched physics backends: MJX on the accelerator and CPU MuJoCo, behind one interface.

Both step a batch of environments shaped (S, E) = (seeds, envs per seed) through one agent step:
`action_repeat` control steps ("frames"), each `n_sub_steps` physics steps with the action held,
summing the task reward after every control step (as dm_control plus DrQ-v2's action-repeat
wrapper do). Episode starts are computed on the host (`envs/dmc.py`) and handed in as qpos/qvel.

Interface (both backends):
    state = backend.init(qpos, qvel)          # [S,E,nq], [S,E,nv] numpy -> backend state
    state, reward = backend.step(state, action)   # action f32 [S,E,A]; reward f32 [S,E]
    state = backend.where(reset, new, old)    # per-env select, reset: bool [S,E] numpy
    backend.qpos(state)                       # [S,E,nq] (device array or numpy)

With `sharding` (a NamedSharding of the seeds axis, `dear_jax/devices.py`), MJX uploads its starts
with it and its programs return states with it, so each device steps its block of seeds.

MJX solver settings (`SolverSettings`) are the speed knob. dm_control's XMLs use MuJoCo's
defaults (Newton, 100 iterations, 50 line-search iterations; finger 200). Measured on CPU for
walker-walk with a fixed sinusoidal action sequence (4 envs, 25 agent steps, against CPU MuJoCo
with dm_control's options; tests/test_physics.py keeps the default honest), as
(iterations, ls_iterations):
    (6, 10): identical to 4 decimals.
    (4, 3) = (4, 5): max |qpos| error 0.01 after 5 agent steps, 0.15 after 25 (the walker is
        chaotic once it touches the floor), per-step rewards within 0.085, returns within 2%.
    (4, 5) without Euler damping: 0.005 / 0.16, rewards within 0.057, returns within 1%.
    (3, 5): returns off by 9%. (2, 5), (2, 50): qpos off by 1.5 after 10 steps, returns by 30%.
    (4, 5) CG: qpos off by 0.34 after 10 steps. (1, *): NaN (MJX's single-iteration path).
H100, 5 x 8 envs, ms per walker agent step (20 physics steps; benchmarks/results/envs_h100.json):
    (4, 5) 24.9, (4, 3) 19.2, (3, 5) 18.3, (4, 5) no Euler damping 22.1, (3, 3) no Euler
    damping 16.8, (4, 5) CG 20.4, (6, 10) 38.0; unrolling the substep scan or XLA command
    buffers for while loops did not help (30.3 and 26.6 ms).
Default: (4, 3), the fastest measured setting that keeps dm_control's behaviour. `None` keeps
the model's own value.

CPU MuJoCo steps exactly as dm_control's legacy stepping does (`mj_step2`, `mj_step` x (n-1),
`mj_step1`, so position/velocity fields match the new state when the reward is read). The MJX
backend uses `mjx.step` x n and then recomputes the position- and velocity-stage quantities a
reward reads (kinematics, centre-of-mass, sensors), which is the same state.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import dataclasses
import io
import logging

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

# mujoco.mjx prints "Failed to import warp" when the optional Warp backend is absent (it is never
# used here: impl="jax"); the text goes to the log instead of every process's console.
with contextlib.redirect_stdout(io.StringIO()) as _import_noise:
    from mujoco import mjx
if _import_noise.getvalue().strip():
    logging.getLogger(__name__).info(
        "mujoco.mjx import: %s", _import_noise.getvalue().strip(), extra={"console": False}
    )

from envs.dmc import PhysicsView, view_from_mjdata, write_view  # noqa: E402

BACKENDS = ("mjx", "cpu", "auto")


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """MJX solver options (the CPU backend always uses the model's own)."""

    iterations: int | None = 4  # Newton iterations per physics step; None: the XML's (100)
    ls_iterations: int | None = 3  # line-search iterations; None: the XML's (50)
    unroll: int = 1  # unroll of the scan over physics steps (GPU: fewer loop round trips)
    solver: str | None = None  # "newton" | "cg"; None: the XML's (Newton)
    euler_damping: bool | None = None  # implicit joint damping in Euler; None: the XML's (on)


def resolve_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown physics backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "auto":
        return "mjx" if jax.default_backend() != "cpu" else "cpu"
    return backend


def _compiler_options() -> dict | None:
    """XLA options for the MJX programs on the platform they compile for.

    XLA:CPU's fusion emitters (on by default in jax 0.10) inline chains of cheap elementwise
    ops into every consumer, so MJX's kinematics down a deep body chain recomputes each parent
    pose exponentially often: the 10-body Franka chain of the kitchen took 23 ms per
    `mjx.kinematics` call with them and 0.4 ms without; one kitchen agent step (2 envs, 40
    physics steps) 2.9 s -> 0.15 s, its compile 30 -> 22 s of CPU; walker 5 -> 3 ms per step.
    Only the CPU platform gets the option (GPU fusion is a different compiler).
    """
    if jax.default_backend() == "cpu":
        return {"xla_cpu_use_fusion_emitters": False}
    return None


def _vmap2(fn):
    """vmap over the (S, E) leading axes."""
    return jax.vmap(jax.vmap(fn))


# --------------------------------------------------------------------------------------------
# MJX


def _reward_view(m: mjx.Model, d: mjx.Data) -> PhysicsView:
    """Position/velocity-stage fields for the current qpos/qvel, without collision or solver."""
    d = mjx.kinematics(m, d)
    d = mjx.com_pos(m, d)
    d = mjx.sensor_pos(m, d)
    d = mjx.com_vel(m, d)
    d = mjx.sensor_vel(m, d)
    return PhysicsView(
        qpos=d.qpos,
        qvel=d.qvel,
        ctrl=d.ctrl,
        xpos=d.xpos,
        xmat=d.xmat,
        site_xpos=d.site_xpos,
        sensordata=d.sensordata,
    )


class MjxPhysics:
    """MJX physics, vmapped over (S, E); one jitted function per agent step."""

    name = "mjx"
    on_host = False  # dispatched from the calling thread (which waits on its loops' conditions)

    def __init__(
        self,
        model: mujoco.MjModel,
        reward_fn,
        *,
        n_sub_steps: int,
        action_repeat: int,
        solver: SolverSettings = SolverSettings(),
        control=None,
        sharding: jax.sharding.Sharding | None = None,
    ):
        model = _copy_model(model)
        if solver.iterations is not None:
            model.opt.iterations = solver.iterations
        if solver.ls_iterations is not None:
            model.opt.ls_iterations = solver.ls_iterations
        if solver.solver is not None:
            kinds = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}
            if solver.solver not in kinds:
                raise ValueError(f"unknown solver {solver.solver!r}; valid: newton, cg")
            model.opt.solver = kinds[solver.solver]
        if solver.euler_damping is not None:
            bit = int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
            if solver.euler_damping:
                model.opt.disableflags &= ~bit
            else:
                model.opt.disableflags |= bit
        self.mj_model = model
        self.solver = solver
        self.n_sub_steps = n_sub_steps
        self.action_repeat = action_repeat
        self.control = control
        self.sharding = sharding
        self._m = mjx.put_model(model, impl="jax")
        self._reward_fn = reward_fn
        options = _compiler_options()
        # Every output leaf leads with (S, E): pinning the outputs keeps each seed's state on
        # its device, constants (fresh data's zeros) included.
        placed = {} if sharding is None else {"out_shardings": sharding}
        self._step = jax.jit(_vmap2(self._step_one), compiler_options=options, **placed)
        self._init = jax.jit(_vmap2(self._init_one), compiler_options=options, **placed)
        self._where = jax.jit(
            lambda reset, new, old: jax.tree.map(
                lambda a, b: jnp.where(reset.reshape(reset.shape + (1,) * (a.ndim - 2)), a, b),
                new,
                old,
            ),
            **placed,
        )

    def _init_one(self, qpos, qvel):
        # No mjx.forward here: `mjx.step` recomputes every derived field from qpos/qvel (and
        # forward leaves the warm start alone), so the steps are identical without it, as on
        # the CPU backend, and the init program compiles in a moment instead of costing a
        # second compile of the whole forward pass (40 s of CPU for the kitchen).
        d = mjx.make_data(self._m)
        return d.replace(qpos=qpos.astype(d.qpos.dtype), qvel=qvel.astype(d.qvel.dtype))

    def _step_one(self, d: mjx.Data, action: jax.Array):
        m = self._m
        d = d.replace(ctrl=action.astype(d.ctrl.dtype))

        def physics_step(d, _):
            return mjx.step(m, d), None

        def control_step(d, _):
            if self.control is not None:
                d = d.replace(ctrl=self.control(d.qpos, action, jnp).astype(d.ctrl.dtype))
            d, _ = jax.lax.scan(
                physics_step, d, None, length=self.n_sub_steps, unroll=self.solver.unroll
            )
            return d, self._reward_fn(_reward_view(m, d))

        d, rewards = jax.lax.scan(control_step, d, None, length=self.action_repeat)
        return d, rewards.sum().astype(jnp.float32)

    def init(self, qpos: np.ndarray, qvel: np.ndarray) -> mjx.Data:
        qpos, qvel = (np.asarray(x, np.float32) for x in (qpos, qvel))
        return self._init(upload(qpos, self.sharding), upload(qvel, self.sharding))

    def step(self, state: mjx.Data, action: jax.Array):
        return self._step(state, action)

    def where(self, reset: np.ndarray, new: mjx.Data, old: mjx.Data) -> mjx.Data:
        return self._where(upload(np.asarray(reset, bool), self.sharding), new, old)

    def qpos(self, state: mjx.Data) -> jax.Array:
        return state.qpos


# --------------------------------------------------------------------------------------------
# CPU MuJoCo


@dataclasses.dataclass(frozen=True)
class CpuState:
    """Host state of a batch; enough to resume dm_control's legacy stepping exactly."""

    qpos: np.ndarray  # f64 [S,E,nq]
    qvel: np.ndarray  # f64 [S,E,nv]
    act: np.ndarray  # f64 [S,E,na]
    qacc_warmstart: np.ndarray  # f64 [S,E,nv]
    time: np.ndarray  # f64 [S,E]


class CpuPhysics:
    """CPU MuJoCo with dm_control's stepping: a Python loop over the batch, split over `threads`
    threads (MuJoCo's calls release the GIL), each with its own MjData. Every env is stepped
    from its own state alone (the `CpuState` fields, loaded before each step), so any number of
    threads gives the same result; models with state outside them (mocap bodies, user data,
    plugins) are refused."""

    name = "cpu"
    on_host = True  # steps on the host (the env's thread and its `threads`), not dispatched

    def __init__(
        self,
        model: mujoco.MjModel,
        reward_fn,
        *,
        n_sub_steps: int,
        action_repeat: int,
        control=None,
        threads: int = 1,
    ):
        if threads < 1:
            raise ValueError(f"physics threads must be >= 1, got {threads}")
        unloaded = {"mocap bodies": model.nmocap, "user data": model.nuserdata}
        unloaded["plugins"] = model.nplugin
        if any(unloaded.values()):
            raise ValueError(
                "CPU physics loads each env's qpos, qvel, act, warm start and time only; this "
                f"model also has state in {', '.join(k for k, n in unloaded.items() if n)}"
            )
        self.mj_model = model
        self.n_sub_steps = n_sub_steps
        self.action_repeat = action_repeat
        self.control = control
        self.threads = threads
        self._datas = [mujoco.MjData(model) for _ in range(threads)]
        self._pool = (
            concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="physics")
            if threads > 1
            else None
        )
        self._reward = jax.jit(_vmap2(jax.vmap(reward_fn)))
        self._cpu = jax.local_devices(backend="cpu")[0]
        self._view = view_from_mjdata(self._datas[0])  # the shapes of one env's view

    @staticmethod
    def _load(d: mujoco.MjData, state: CpuState, idx) -> mujoco.MjData:
        d.qpos[:] = state.qpos[idx]
        d.qvel[:] = state.qvel[idx]
        d.act[:] = state.act[idx]
        d.qacc_warmstart[:] = state.qacc_warmstart[idx]
        d.time = state.time[idx]
        return d

    def init(self, qpos: np.ndarray, qvel: np.ndarray) -> CpuState:
        shape = qpos.shape[:2]
        m = self.mj_model
        return CpuState(
            qpos=np.asarray(qpos, np.float64).copy(),
            qvel=np.asarray(qvel, np.float64).copy(),
            act=np.zeros(shape + (m.na,)),
            qacc_warmstart=np.zeros(shape + (m.nv,)),
            time=np.zeros(shape),
        )

    def _control_step(self, d: mujoco.MjData) -> None:
        m = self.mj_model
        if m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
            mujoco.mj_step(m, d, self.n_sub_steps)
        else:
            mujoco.mj_step2(m, d)
            if self.n_sub_steps > 1:
                mujoco.mj_step(m, d, self.n_sub_steps - 1)
        mujoco.mj_step1(m, d)

    def _step_envs(self, d, state, new, views, action, envs) -> None:
        """Step the envs [(s, e), ...] one agent step on in `d`, writing their new state into
        `new` and their reward views after each of the `action_repeat` control steps into
        `views` ([S, E, R] leaves)."""
        for s, e in envs:
            self._load(d, state, (s, e))
            # step1 refreshes the position/velocity stage for the loaded state: dm_control's
            # data sits right after its previous control step's mj_step1.
            mujoco.mj_step1(self.mj_model, d)
            d.ctrl[:] = action[s, e]
            for r in range(self.action_repeat):
                if self.control is not None:
                    d.ctrl[:] = self.control(d.qpos, action[s, e], np)
                self._control_step(d)
                write_view(views, (s, e, r), d)
            for k in new:
                new[k][s, e] = getattr(d, k)

    def step(self, state: CpuState, action) -> tuple[CpuState, np.ndarray]:
        action = np.asarray(action, np.float64)
        num_s, num_e = state.qpos.shape[:2]
        new = {k: np.copy(v) for k, v in dataclasses.asdict(state).items()}
        shape = (num_s, num_e, self.action_repeat)
        views = jax.tree.map(lambda x: np.empty(shape + x.shape, x.dtype), self._view)
        envs = list(np.ndindex(num_s, num_e))
        if self._pool is None:
            self._step_envs(self._datas[0], state, new, views, action, envs)
        else:  # contiguous blocks of envs, one per thread
            blocks = np.array_split(envs, self.threads)
            parts = [
                self._pool.submit(self._step_envs, d, state, new, views, action, block)
                for d, block in zip(self._datas, blocks, strict=True)
            ]
            # Every block ends before any error is raised: no thread still steps its MjData
            # when the next step hands it new work.
            concurrent.futures.wait(parts)
            for part in parts:
                part.result()
        with jax.default_device(self._cpu):
            per_frame = np.asarray(self._reward(views), np.float32)  # [S,E,R]
        return CpuState(**new), per_frame.sum(-1, dtype=np.float32)

    def where(self, reset: np.ndarray, new: CpuState, old: CpuState) -> CpuState:
        reset = np.asarray(reset)
        return jax.tree.map(
            lambda a, b: np.where(reset.reshape(reset.shape + (1,) * (a.ndim - 2)), a, b),
            new,
            old,
        )

    def qpos(self, state: CpuState) -> np.ndarray:
        return state.qpos

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


jax.tree_util.register_dataclass(
    CpuState, data_fields=["qpos", "qvel", "act", "qacc_warmstart", "time"], meta_fields=[]
)


def upload(x: np.ndarray, sharding: jax.sharding.Sharding | None) -> jax.Array:
    """A host array [S, E, ...] on the device(s): split by seed with a `sharding`, else on the
    default device, uncommitted."""
    return jnp.asarray(x) if sharding is None else jax.device_put(x, sharding)


def _copy_model(model: mujoco.MjModel) -> mujoco.MjModel:
    return copy.copy(model)


def make_physics(
    backend: str,
    model: mujoco.MjModel,
    reward_fn,
    *,
    n_sub_steps: int,
    action_repeat: int,
    solver: SolverSettings = SolverSettings(),
    control=None,
    sharding: jax.sharding.Sharding | None = None,
    threads: int = 1,
):
    """Build the named backend ("mjx", "cpu" or "auto").

    control: None (ctrl = action) or `control(qpos, action, xp) -> ctrl`, evaluated at the start
    of every control step with xp = jax.numpy (MJX) or numpy (CPU), e.g. the kitchen's joint
    velocity -> position target mapping. sharding: where MJX keeps the (S, E) states (None: the
    default device); CPU MuJoCo's state is on the host. threads: CPU MuJoCo's threads.
    """
    backend = resolve_backend(backend)
    if backend == "mjx":
        return MjxPhysics(
            model,
            reward_fn,
            n_sub_steps=n_sub_steps,
            action_repeat=action_repeat,
            solver=solver,
            control=control,
            sharding=sharding,
        )
    return CpuPhysics(
        model,
        reward_fn,
        n_sub_steps=n_sub_steps,
        action_repeat=action_repeat,
        control=control,
        threads=threads,
    )
