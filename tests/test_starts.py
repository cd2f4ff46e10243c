"""Episode starts against dm_control's laws, for every registered DMC task.

Starts are drawn through the env's own reset path (`Env._initial_states` on a stand-in that
holds only what it reads), N per task from one RandomState, on CPU MuJoCo. Each law below names
the dm_control 1.0.50 function it comes from. Two kinds of check:
- the law: every randomised coordinate inside its range, reaching near both ends, mean, std and
  empirical CDF within a few standard errors of the law's; coordinates dm_control leaves alone
  stay at qpos0, qvel stays 0 unless the task draws it; no contact where dm_control rejects
  contacts (against a rejection sampler written here, since rejection reshapes the marginals);
- the stream: from one seed, the numbers dm_control draws in its order (joint order, one draw
  per randomised coordinate, redraws for rejections), so a seed gives dm_control's starts.
Bounds are 4.5 standard errors (KS at the 0.1% level): loose enough for any seed.
"""

import dataclasses
import math
import types

import mujoco
import numpy as np
import pytest

import envs
from envs import dmc
from envs.base import Env

N = 400  # starts per task
WALKER_LEGS = ("right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle")
CHEETAH_LEGS = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
Z = 4.5  # standard errors allowed
KS_C = 1.95  # Kolmogorov-Smirnov critical constant at the 0.1% level


@dataclasses.dataclass(frozen=True)
class Law:
    """One task's start law. `uniform`: joint -> (lo, hi), None for the joint's own range;
    `normal_qpos` / `normal_qvel`: joint -> (mean, std); `reject_contacts`: redrawn until the
    forward pass finds no contact (the uniform law then holds before the rejection)."""

    uniform: dict = dataclasses.field(default_factory=dict)
    normal_qpos: dict = dataclasses.field(default_factory=dict)
    normal_qvel: dict = dataclasses.field(default_factory=dict)
    reject_contacts: bool = False
    fixed_qvel: bool = True  # qvel stays 0


# walker: `PlanarWalker.initialize_episode` -> `randomizers.randomize_limited_and_rotational_
# joints`: the unlimited hinge rooty over [-pi, pi], the limited leg hinges over their ranges;
# the unlimited slides rootz and rootx untouched.
_WALKER = Law(uniform={"rooty": (-np.pi, np.pi), **{j: None for j in WALKER_LEGS}})

LAWS = {
    "walker-walk": _WALKER,
    "walker-stand": _WALKER,
    "walker-run": _WALKER,
    # finger: `Spin.initialize_episode` -> `_set_random_joint_angles`: the randomizer over all
    # joints (limited proximal and distal over their ranges, the spinner's unlimited `hinge` over
    # [-pi, pi]), redrawn until no contact.
    "finger-spin": Law(
        uniform={"proximal": None, "distal": None, "hinge": (-np.pi, np.pi)},
        reject_contacts=True,
    ),
    # ball_in_cup: `BallInCup.initialize_episode`: ball x over [-0.2, 0.2], z over [0.2, 0.5],
    # redrawn until no contact; the cup stays at 0.
    "ball_in_cup-catch": Law(
        uniform={"ball_x": (-0.2, 0.2), "ball_z": (0.2, 0.5)}, reject_contacts=True
    ),
    # cheetah: `Cheetah.initialize_episode`: the limited joints over their ranges (the root
    # joints stay), then 200 settling steps; the law is checked with settling switched off,
    # the settling by the stream test.
    "cheetah-run": Law(uniform={j: None for j in CHEETAH_LEGS}, fixed_qvel=False),
    # cartpole: `Balance.initialize_episode` with swing_up: slider 0.01 N, pole pi + 0.01 N,
    # every qvel 0.01 N.
    "cartpole-swingup": Law(
        normal_qpos={"slider": (0.0, 0.01), "hinge_1": (np.pi, 0.01)},
        normal_qvel={"slider": (0.0, 0.01), "hinge_1": (0.0, 0.01)},
        fixed_qvel=False,
    ),
}


def _env_starts(name, n=N, seed=0):
    """n starts of `name` through `Env._initial_states`: model, qpos [n, nq], qvel [n, nv]."""
    task = dmc.TASKS[name]
    model = task.physics_model()
    stand_in = types.SimpleNamespace(
        task=task,
        _model=model,
        _data=mujoco.MjData(model),
        shape=(1, n),
        _rng=np.random.RandomState(seed),
    )
    qpos, qvel = Env._initial_states(stand_in, np.ones((1, n), bool))
    return model, qpos[0], qvel[0]


_CACHE = {}


def _starts(name):
    if name not in _CACHE:
        _CACHE[name] = _env_starts(name)
    return _CACHE[name]


def _ncon(model, qpos, qvel):
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, data)
    return data.ncon


def _range(model, joint, bounds):
    return tuple(model.joint(joint).range) if bounds is None else bounds


# ---------------------------------------------------------------------------------------------
# Statistics helpers.


def _ks(x, cdf):
    x = np.sort(x)
    n = len(x)
    f = cdf(x)
    return max((np.arange(1, n + 1) / n - f).max(), (f - np.arange(n) / n).max())


def _ks2(x, y):
    grid = np.sort(np.concatenate([x, y]))
    fx = np.searchsorted(np.sort(x), grid, side="right") / len(x)
    fy = np.searchsorted(np.sort(y), grid, side="right") / len(y)
    return np.abs(fx - fy).max()


def _check_uniform(x, lo, hi, what):
    n, width = len(x), hi - lo
    assert (x >= lo).all() and (x <= hi).all(), (what, x.min(), x.max(), lo, hi)
    # The gap to each end is about width / n; 8 times that happens with probability e^-8.
    assert x.min() - lo < 8 * width / n and hi - x.max() < 8 * width / n, (what, x.min(), x.max())
    sd = width / math.sqrt(12)
    assert abs(x.mean() - (lo + hi) / 2) < Z * sd / math.sqrt(n), (what, x.mean())
    # The sample std of a uniform law has standard error about sd * sqrt(0.2 / n).
    assert abs(x.std() - sd) < Z * sd * math.sqrt(0.2 / n), (what, x.std(), sd)
    assert _ks(x, lambda v: (v - lo) / width) < KS_C / math.sqrt(n), what


def _check_normal(x, mean, sd, what):
    n = len(x)
    assert abs(x.mean() - mean) < Z * sd / math.sqrt(n), (what, x.mean(), mean)
    assert abs(x.std() - sd) < Z * sd / math.sqrt(2 * n), (what, x.std(), sd)
    cdf = np.vectorize(lambda v: 0.5 * (1 + math.erf((v - mean) / (sd * math.sqrt(2)))))
    assert _ks(x, cdf) < KS_C / math.sqrt(n), what


def _check_same_law(x, ref, lo, hi, what):
    """x against samples `ref` of the same law (both inside [lo, hi])."""
    n, m = len(x), len(ref)
    assert (x >= lo).all() and (x <= hi).all(), (what, x.min(), x.max(), lo, hi)
    se = math.sqrt(ref.var() / n + ref.var() / m)
    assert abs(x.mean() - ref.mean()) < Z * se, (what, x.mean(), ref.mean())
    assert abs(x.std() - ref.std()) < Z * ref.std() * math.sqrt(0.5 / n + 0.5 / m), (
        what,
        x.std(),
        ref.std(),
    )
    assert _ks2(x, ref) < KS_C * math.sqrt((n + m) / (n * m)), what


def _rejection_reference(model, law, m=6000, seed=123):
    """Uniform candidates over `law.uniform` from qpos0, kept where nothing touches."""
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(model)
    kept = []
    for _ in range(m):
        mujoco.mj_resetData(model, data)
        for joint, bounds in law.uniform.items():
            lo, hi = _range(model, joint, bounds)
            data.qpos[model.joint(joint).qposadr[0]] = rng.uniform(lo, hi)
        mujoco.mj_forward(model, data)
        if data.ncon == 0:
            kept.append(data.qpos.copy())
    return np.array(kept)


# ---------------------------------------------------------------------------------------------
# The laws.


def test_every_registered_task_has_a_start_law():
    # The kitchen starts from D4RL's fixed state (tests/test_kitchen.py); every DMC task has one.
    from envs import kitchen

    assert set(envs.names()) - set(kitchen.TASKS) == set(LAWS), set(envs.names()) ^ set(LAWS)


def test_required_joints_are_randomised_by_name():
    # The walker's legs and the finger's joints: left out, they would start the same each time.
    assert set(WALKER_LEGS) <= set(LAWS["walker-walk"].uniform)
    assert {"proximal", "distal", "hinge"} <= set(LAWS["finger-spin"].uniform)


@pytest.mark.parametrize("name", sorted(LAWS))
def test_randomised_coordinates_follow_the_law(name, monkeypatch):
    law = LAWS[name]
    if name.startswith("cheetah"):
        monkeypatch.setattr(dmc, "CHEETAH_SETTLE_STEPS", 0)
        model, qpos, qvel = _env_starts(name)
    else:
        model, qpos, qvel = _starts(name)
    ref = _rejection_reference(model, law) if law.reject_contacts else None
    for joint, bounds in law.uniform.items():
        lo, hi = _range(model, joint, bounds)
        x = qpos[:, model.joint(joint).qposadr[0]]
        if ref is None:
            _check_uniform(x, lo, hi, joint)
        else:
            _check_same_law(x, ref[:, model.joint(joint).qposadr[0]], lo, hi, joint)
    for joint, (mean, sd) in law.normal_qpos.items():
        _check_normal(qpos[:, model.joint(joint).qposadr[0]], mean, sd, joint)
    for joint, (mean, sd) in law.normal_qvel.items():
        _check_normal(qvel[:, model.joint(joint).dofadr[0]], mean, sd, f"{joint} qvel")


@pytest.mark.parametrize("name", sorted(LAWS))
def test_other_coordinates_keep_their_defaults(name, monkeypatch):
    law = LAWS[name]
    if name.startswith("cheetah"):
        monkeypatch.setattr(dmc, "CHEETAH_SETTLE_STEPS", 0)
        model, qpos, qvel = _env_starts(name, n=50)
    else:
        model, qpos, qvel = _starts(name)
    drawn = {model.joint(j).qposadr[0] for j in (*law.uniform, *law.normal_qpos)}
    for j in range(model.njnt):
        adr = model.jnt_qposadr[j]
        if adr not in drawn:
            np.testing.assert_array_equal(qpos[:, adr], model.qpos0[adr], model.joint(j).name)
    if law.fixed_qvel:
        np.testing.assert_array_equal(qvel, 0.0)


@pytest.mark.parametrize("name", sorted(n for n, law in LAWS.items() if law.reject_contacts))
def test_rejected_tasks_start_without_contacts(name):
    model, qpos, qvel = _starts(name)
    assert all(_ncon(model, p, v) == 0 for p, v in zip(qpos, qvel, strict=True))


# ---------------------------------------------------------------------------------------------
# The stream: the same numbers as dm_control from the same seed.

K = 40  # starts compared per task


def _first_free(model, draw):
    """dm_control's rejection loops: redraw (consuming the stream) until nothing touches."""
    data = mujoco.MjData(model)
    while True:
        mujoco.mj_resetData(model, data)
        draw(data)
        mujoco.mj_forward(model, data)
        if data.ncon == 0:
            return data.qpos.copy(), data.qvel.copy()


def _walker_expected(model, rng):
    qpos = model.qpos0.copy()
    # Joint order: rootz, rootx (no draw), rooty, then the legs.
    qpos[model.joint("rooty").qposadr[0]] = rng.uniform(-np.pi, np.pi)
    for joint in WALKER_LEGS:
        qpos[model.joint(joint).qposadr[0]] = rng.uniform(*model.joint(joint).range)
    return qpos, np.zeros(model.nv)


def _finger_expected(model, rng):
    def draw(data):
        for joint in ("proximal", "distal"):
            data.qpos[model.joint(joint).qposadr[0]] = rng.uniform(*model.joint(joint).range)
        data.qpos[model.joint("hinge").qposadr[0]] = rng.uniform(-np.pi, np.pi)

    return _first_free(model, draw)


def _ball_in_cup_expected(model, rng):
    def draw(data):
        data.qpos[model.joint("ball_x").qposadr[0]] = rng.uniform(-0.2, 0.2)
        data.qpos[model.joint("ball_z").qposadr[0]] = rng.uniform(0.2, 0.5)

    return _first_free(model, draw)


def _cheetah_expected(model, rng):
    # Physics.reset's forward pass at qpos0, the draw, then Physics.step(200) with legacy
    # stepping: mj_step2 on the stale position stage, mj_step x 199, mj_step1; clock to 0.
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    lows, highs = np.array([model.joint(j).range for j in CHEETAH_LEGS]).T
    draws = rng.uniform(lows, highs)
    for joint, value in zip(CHEETAH_LEGS, draws, strict=True):
        data.qpos[model.joint(joint).qposadr[0]] = value
    mujoco.mj_step2(model, data)
    mujoco.mj_step(model, data, 199)
    mujoco.mj_step1(model, data)
    return data.qpos.copy(), data.qvel.copy()


def _cartpole_expected(model, rng):
    qpos = np.array([0.01 * rng.randn(), np.pi + 0.01 * rng.randn()])
    return qpos, 0.01 * rng.randn(2)


EXPECTED = {
    "walker": _walker_expected,
    "finger": _finger_expected,
    "ball_in_cup": _ball_in_cup_expected,
    "cheetah": _cheetah_expected,
    "cartpole": _cartpole_expected,
}


@pytest.mark.parametrize("name", sorted(LAWS))
def test_one_seed_gives_dm_controls_starts(name):
    model, qpos, qvel = _env_starts(name, n=K, seed=7)
    rng = np.random.RandomState(7)
    for i in range(K):
        want_qpos, want_qvel = EXPECTED[dmc.TASKS[name].domain](model, rng)
        np.testing.assert_allclose(qpos[i], want_qpos, rtol=0, atol=1e-12, err_msg=f"start {i}")
        np.testing.assert_allclose(qvel[i], want_qvel, rtol=0, atol=1e-12, err_msg=f"start {i}")


def test_cheetah_settles_before_the_episode():
    model, qpos, qvel = _starts("cheetah-run")
    # 200 steps of falling: the legs left their drawn values and the body rests on the floor
    # with nearly no speed left (dm_control starts the episode from here, clock at 0).
    assert np.abs(qvel).max() > 0
    assert np.median(np.abs(qvel)) < 0.5
    assert all(_ncon(model, p, v) > 0 for p, v in zip(qpos[:20], qvel[:20], strict=True))


# ---------------------------------------------------------------------------------------------
# The randomizer's rules for joint kinds no registered task has (ball and free joints).

_KINDS_XML = """
<mujoco>
  <worldbody>
    <body><joint name="free" type="free"/><geom size="0.1"/></body>
    <body pos="1 0 0"><joint name="ball_limited" type="ball" range="0 60"/><geom size="0.1"/></body>
    <body pos="2 0 0"><joint name="ball" type="ball"/><geom size="0.1"/></body>
    <body pos="3 0 0">
      <joint name="slide" type="slide"/>
      <joint name="slide_limited" type="slide" range="-1 2" axis="0 0 1"/>
      <geom size="0.1"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_randomizer_rules_for_every_joint_kind():
    # `randomizers.randomize_limited_and_rotational_joints` and `random_limited_quaternion`.
    model = mujoco.MjModel.from_xml_string(_KINDS_XML)
    data = mujoco.MjData(model)
    rng, mirror = np.random.RandomState(3), np.random.RandomState(3)
    adr = {name: model.joint(name).qposadr[0] for name in ("free", "ball_limited", "ball")}
    limit = model.joint("ball_limited").range[1]
    free_q, lim_q, ball_q, slides = [], [], [], []
    for _ in range(N):
        mujoco.mj_resetData(model, data)
        dmc._randomize_limited_and_rotational_joints(model, data, rng)
        # The stream in joint order: free `rand(4)`; limited ball `randn(3)` axis and
        # `rand() * limit` angle; ball `randn(4)`; unlimited slide nothing; limited slide uniform.
        q = mirror.rand(4)
        np.testing.assert_allclose(
            data.qpos[adr["free"] + 3 : adr["free"] + 7], q / np.linalg.norm(q)
        )
        axis = mirror.randn(3)
        angle = mirror.rand() * limit
        axis /= np.linalg.norm(axis)
        want = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
        np.testing.assert_allclose(data.qpos[adr["ball_limited"] : adr["ball_limited"] + 4], want)
        q = mirror.randn(4)
        np.testing.assert_allclose(data.qpos[adr["ball"] : adr["ball"] + 4], q / np.linalg.norm(q))
        assert data.qpos[model.joint("slide_limited").qposadr[0]] == mirror.uniform(-1, 2)
        free_q.append(data.qpos[adr["free"] : adr["free"] + 7].copy())
        lim_q.append(data.qpos[adr["ball_limited"] : adr["ball_limited"] + 4].copy())
        ball_q.append(data.qpos[adr["ball"] : adr["ball"] + 4].copy())
        slides.append(data.qpos[[model.joint(j).qposadr[0] for j in ("slide", "slide_limited")]])
    free_q, lim_q, ball_q, slides = map(np.array, (free_q, lim_q, ball_q, slides))
    # Free joint: position untouched, quaternion a unit vector in the positive orthant.
    assert (free_q[:, :3] == model.qpos0[:3]).all()
    np.testing.assert_allclose(np.linalg.norm(free_q[:, 3:], axis=1), 1.0)
    assert (free_q[:, 3:] >= 0).all()
    # Limited ball: rotation angle uniform over [0, range max].
    _check_uniform(2 * np.arccos(np.clip(lim_q[:, 0], -1, 1)), 0.0, limit, "ball angle")
    # Unlimited ball: uniform on the unit 3-sphere (each component has mean 0, variance 1/4).
    np.testing.assert_allclose(np.linalg.norm(ball_q, axis=1), 1.0)
    # (q_i^2 is Beta(1/2, 3/2): mean 1/4, std 1/4.)
    assert np.abs(ball_q.mean(0)).max() < Z * 0.5 / math.sqrt(N), ball_q.mean(0)
    assert np.abs((ball_q**2).mean(0) - 0.25).max() < Z * 0.25 / math.sqrt(N), ball_q.var(0)
    # Unlimited slide untouched; limited slide uniform over its range.
    np.testing.assert_array_equal(slides[:, 0], 0.0)
    _check_uniform(slides[:, 1], -1.0, 2.0, "slide_limited")
