"""A replay buffer that lives on the accelerator, one per seed (vmap it over seeds).

It stores single uint8 frames and masks of E parallel environments in a ring of T rows
([T, E, ...]; a row is one batched environment step), plus the action that led to each frame,
rewards, discounts and an episode id per entry. Frame stacks, n-step returns and TED's
same-episode frames are rebuilt at sample time, so memory is that of single frames
(docs/method.md, Hyperparameters: a stacked 250k buffer would need ~21 GB per seed).

Conventions (dm_env / DrQ-v2): entry (t, e) holds the timestep returned by the environment; its
`action` is the action that produced it (zeros on the first step of an episode). The transition
sampled at (t, e) is: obs = stack(t), action = action[t+1], reward = sum_k gamma^(k-1) r[t+k],
discount = gamma^n' prod_k d[t+k], next_obs = stack(t+n'), where n' <= n stops at the end of the
episode and at the newest row: a transition never crosses an episode boundary.
"""

from __future__ import annotations

import math
import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class ReplayState:
    frames: jax.Array  # uint8 [T, E, H, W, C]
    masks: jax.Array  # uint8 [T, E, H, W]
    actions: jax.Array  # f32 [T, E, A]
    rewards: jax.Array  # f32 [T, E]
    discounts: jax.Array  # f32 [T, E]
    episode: jax.Array  # int32 [T, E]: episode id of the entry, counted per environment
    episodes_started: jax.Array  # int32 [E]
    pos: jax.Array  # int32 []: next row to write
    size: jax.Array  # int32 []: rows written so far, at most T

    @property
    def rows(self) -> int:
        return self.frames.shape[0]


@struct.dataclass
class Batch:
    obs: jax.Array  # uint8 [B, H, W, C*K], oldest frame first
    action: jax.Array  # f32 [B, A]
    reward: jax.Array  # f32 [B]
    discount: jax.Array  # f32 [B]
    next_obs: jax.Array  # uint8 [B, H, W, C*K]
    mask: jax.Array  # uint8 [B, H, W, K]: agent masks of obs's frames
    far_obs: jax.Array | None = None  # uint8 [B, H, W, C*K]: same episode, >= 2 steps from obs
    far_valid: jax.Array | None = None  # f32 [B]: 1 where the episode has such a step stored


def entry_bytes(frame_shape: tuple[int, int, int], action_dim: int) -> int:
    """Bytes one (row, env) entry takes: frame, mask, action, reward, discount, episode id."""
    h, w, c = frame_shape
    return h * w * c + h * w + 4 * action_dim + 4 + 4 + 4


def replay_bytes(num_seeds: int, capacity: int, frame_shape, action_dim: int) -> int:
    return num_seeds * capacity * entry_bytes(tuple(frame_shape), action_dim)


def available_bytes(device: jax.Device | None = None) -> int:
    """Memory free for new buffers on `device` (accelerator memory, or host RAM for the CPU)."""
    device = device or jax.local_devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_fits(
    num_seeds: int,
    capacity: int,
    frame_shape,
    action_dim: int,
    available: int | None = None,
    headroom: float = 0.8,
    lanes: str = "seeds",
) -> int:
    """Raise MemoryError, saying how much is needed, unless the buffers fit in `headroom` of memory.
    `lanes` names what the `num_seeds` buffers are, e.g. "lanes (2 seeds x 3 settings)" or
    "seeds per device (4 over 2 devices)"."""
    need = replay_bytes(num_seeds, capacity, frame_shape, action_dim)
    have = available_bytes() if available is None else available
    if need > headroom * have:
        gib = 2**30
        fits = int(headroom * have / need * capacity)
        raise MemoryError(
            f"replay for {num_seeds} {lanes} x {capacity:,} entries needs {need / gib:.2f} GiB "
            f"({need / num_seeds / gib:.2f} GiB each), but only {have / gib:.2f} GiB is free on "
            f"{jax.devices()[0].platform} and {headroom:.0%} of it may be used; lower "
            f"replay.capacity to at most {fits:,} or run fewer {'seeds or settings' if 'settings' in lanes else 'seeds'}"
        )
    return need


def init(
    capacity: int, num_envs: int, frame_shape, action_dim: int, leading: tuple[int, ...] = ()
) -> ReplayState:
    """Empty buffers of `capacity` entries (rounded up to whole rows of `num_envs`).

    `leading` adds batch axes in front (e.g. (num_seeds,)) so seeds can be vmapped.
    """
    rows = math.ceil(capacity / num_envs)
    h, w, c = frame_shape
    lead = tuple(leading)

    def zeros(shape, dtype):
        return jnp.zeros(lead + shape, dtype)

    return ReplayState(
        frames=zeros((rows, num_envs, h, w, c), jnp.uint8),
        masks=zeros((rows, num_envs, h, w), jnp.uint8),
        actions=zeros((rows, num_envs, action_dim), jnp.float32),
        rewards=zeros((rows, num_envs), jnp.float32),
        discounts=zeros((rows, num_envs), jnp.float32),
        episode=jnp.full(lead + (rows, num_envs), -1, jnp.int32),
        episodes_started=zeros((num_envs,), jnp.int32),
        pos=zeros((), jnp.int32),
        size=zeros((), jnp.int32),
    )


def add(
    state: ReplayState,
    frame: jax.Array,
    mask: jax.Array,
    action: jax.Array,
    reward: jax.Array,
    discount: jax.Array,
    first: jax.Array,
) -> ReplayState:
    """Write one row: the timestep of every environment ([E, ...] each) and the action behind it."""
    chex.assert_shape(first, (state.frames.shape[1],))
    started = state.episodes_started + first.astype(jnp.int32)
    # A first timestep opens a new episode id; every later one belongs to the latest.
    episode = started - 1
    action = jnp.where(first[:, None], 0.0, action)  # nothing led to a reset observation
    p = state.pos

    def put(buf, value):
        return buf.at[p].set(value.astype(buf.dtype))

    return state.replace(
        frames=put(state.frames, frame),
        masks=put(state.masks, mask),
        actions=put(state.actions, action),
        rewards=put(state.rewards, jnp.where(first, 0.0, reward)),
        discounts=put(state.discounts, jnp.where(first, 1.0, discount)),
        episode=put(state.episode, episode),
        episodes_started=started,
        pos=(p + 1) % state.rows,
        size=jnp.minimum(state.size + 1, state.rows),
    )


def _age(state: ReplayState, row: jax.Array) -> jax.Array:
    """How many rows after the oldest stored row `row` is (>= size means not stored)."""
    oldest = jnp.where(state.size == state.rows, state.pos, 0)
    return (row - oldest) % state.rows


def _same_episode_at(state, row, env, offset):
    """Is row+offset stored and of the same episode as (row, env)? Also returns its ring row."""
    target = (row + offset) % state.rows
    age = _age(state, row) + offset
    stored = (age >= 0) & (age < state.size)
    same = state.episode[target, env] == state.episode[row, env]
    return stored & same, target


def sample_weights(state: ReplayState, frame_stack: int) -> jax.Array:
    """[T, E] weights: 1 where a transition may start, 0 elsewhere.

    A start needs a successor in the same episode, and, once the ring has wrapped, a full stack of
    stored history (the oldest rows have lost the frames before them).
    """
    rows = jnp.arange(state.rows)
    age = _age(state, rows)
    full = state.size == state.rows
    history_ok = jnp.where(full, age >= frame_stack - 1, True)
    nxt = (rows + 1) % state.rows
    has_next = (age + 1 < state.size)[:, None] & (state.episode[nxt] == state.episode[rows])
    return (has_next & (age < state.size)[:, None] & history_ok[:, None]).astype(jnp.float32)


def _stack_rows(state, row, env, frame_stack):
    """Rows of the stack ending at `row`, oldest first; frames before the episode start repeat it."""
    rows = [row]
    for k in range(1, frame_stack):
        ok, prev = _same_episode_at(state, row, env, -k)
        rows.append(jnp.where(ok, prev, rows[-1]))
    return jnp.stack(rows[::-1], axis=-1)  # [B, K]


def _gather_stack(buf, rows, env):
    """buf [T, E, H, W, (C)] at rows [B, K], env [B] -> [B, H, W, K*C] (oldest frame first)."""
    x = buf[rows, env[:, None]]  # [B, K, H, W, (C)]
    if x.ndim == 4:
        x = x[..., None]
    b, k, h, w, c = x.shape
    return jnp.moveaxis(x, 1, 3).reshape(b, h, w, k * c)


def sample_at(
    state: ReplayState,
    row: jax.Array,
    env: jax.Array,
    *,
    nstep: int,
    gamma: float,
    frame_stack: int,
    far_key: jax.Array | None = None,
    skip_positives: bool = True,
) -> Batch:
    """The transitions that start at entries (row[b], env[b]); see the module docstring.

    `far_key`, when given, also draws TED's same-episode frame (see `same_episode_offsets`,
    which takes `skip_positives`).
    """
    reward = jnp.zeros(row.shape, jnp.float32)
    discount = jnp.ones(row.shape, jnp.float32)
    alive = jnp.ones(row.shape, bool)
    next_row = row
    for k in range(1, nstep + 1):
        ok, r = _same_episode_at(state, row, env, k)
        alive = alive & ok
        reward = reward + jnp.where(alive, discount * state.rewards[r, env], 0.0)
        discount = jnp.where(alive, discount * gamma * state.discounts[r, env], discount)
        next_row = jnp.where(alive, r, next_row)
    stacks = {"obs": _stack_rows(state, row, env, frame_stack)}
    stacks["next_obs"] = _stack_rows(state, next_row, env, frame_stack)
    if far_key is not None:
        offset, valid = same_episode_offsets(
            state, row, env, far_key, nstep, skip_positives, frame_stack
        )
        stacks["far_obs"] = _stack_rows(state, (row + offset) % state.rows, env, frame_stack)
    # The rows are computed once, before the image gathers: fused into them, the index
    # arithmetic (and its gathers of episode ids) would be redone for every pixel gathered.
    stacks, env = jax.lax.optimization_barrier((stacks, env))
    images = {k: _gather_stack(state.frames, rows, env) for k, rows in stacks.items()}
    batch = Batch(
        obs=images["obs"],
        action=state.actions[(row + 1) % state.rows, env],
        reward=reward,
        discount=discount,
        next_obs=images["next_obs"],
        mask=_gather_stack(state.masks, stacks["obs"], env),
    )
    if far_key is not None:
        batch = batch.replace(far_obs=images["far_obs"], far_valid=valid.astype(jnp.float32))
    # Written out whole: fused into their consumer (the random shift), the gathers would read
    # single bytes of K frames per pixel from all over the buffer.
    return jax.lax.optimization_barrier(batch)


def _episode_span(state, row, env):
    """Ages of the first and last stored entries of the episode of (row, env), each [B].

    For one env, episode ids never decrease with age, so both ends are found by binary search
    over the stored ages (log2(T) gathers) instead of a scan of the episode.
    """
    ep = state.episode[row, env]
    oldest = jnp.where(state.size == state.rows, state.pos, 0)

    def first_age_where(pred):
        # Smallest age in [0, size] whose entry satisfies pred (monotone in age); size if none.
        lo, hi = jnp.zeros_like(row), jnp.broadcast_to(state.size, row.shape)
        for _ in range(max(1, math.ceil(math.log2(state.rows + 1)))):
            mid = (lo + hi) // 2
            hit = pred(state.episode[(oldest + mid) % state.rows, env]) | (lo == hi)
            lo, hi = jnp.where(hit, lo, mid + 1), jnp.where(hit, mid, hi)
        return lo

    start = first_age_where(lambda e: e >= ep)
    end = first_age_where(lambda e: e > ep) - 1
    return start, end


def same_episode_offsets(
    state, row, env, key, nstep: int = 1, skip_positives: bool = True, frame_stack: int = 1
):
    """TED's same-episode negatives: an offset to a uniformly drawn stored step of the same
    episode other than t and t+-1 (as TED's reference samples them), and whether one exists.
    With n-step transitions the positive pair is (t, t+n') for some n' <= nstep, so
    `skip_positives` excludes steps t+1..t+nstep too: a frame is never both the positive and a
    negative (False: t+-1 only, as TED's code, whatever nstep).

    row, env [B] -> (offset int32 [B], valid bool [B]); offset is 0 where none exists.
    """
    ahead = max(2, nstep + 1) if skip_positives else 2  # the first step after t that may be one
    start, end = _episode_span(state, row, env)
    # Once the ring has wrapped, its oldest frame_stack - 1 rows have lost their stacks' frames.
    start = jnp.maximum(start, jnp.where(state.size == state.rows, frame_stack - 1, 0))
    age = _age(state, row)
    lo, hi = start - age, end - age  # lo <= 0 <= hi
    n_before = jnp.maximum(-1 - lo, 0)  # offsets lo..-2
    n_after = jnp.maximum(hi - ahead + 1, 0)  # offsets ahead..hi
    n = n_before + n_after
    u = jnp.floor(jax.random.uniform(key, row.shape) * n).astype(jnp.int32)
    offset = jnp.where(u < n_before, lo + u, ahead + u - n_before)
    valid = n > 0
    return jnp.where(valid, offset, 0), valid


def _draw(key: jax.Array, valid: jax.Array, n: int) -> jax.Array:
    """`n` indices drawn uniformly, with replacement, among the entries where `valid` is nonzero.

    Integer arithmetic only (a running count of valid entries, a uniform integer below the total,
    a binary search for it), so a seed draws the same indices whatever else shares its program,
    and no loop: `jax.random.choice`'s search is a `lax.fori_loop`, which a GPU may run as a
    while loop that waits on the host for its condition at every step.
    """
    count = jnp.cumsum(valid.astype(jnp.int32))
    target = jax.random.randint(key, (n,), 0, count[-1])  # the target-th valid entry, from 0
    lo, hi = jnp.zeros(n, jnp.int32), jnp.full(n, count.shape[0] - 1, jnp.int32)
    for _ in range(max(1, math.ceil(math.log2(count.shape[0])))):  # first i: count[i] > target
        mid = (lo + hi) // 2
        right = count[mid] <= target
        lo, hi = jnp.where(right, mid + 1, lo), jnp.where(right, hi, mid)
    return lo


SAMPLINGS = ("uniform", "episode")  # replay.sampling: every start alike, or DrQ-v2's


def _draw_by_episode(key: jax.Array, state: ReplayState, valid: jax.Array, n: int):
    """`n` starts (row, env) drawn as DrQ-v2's replay draws them: an episode uniformly, then one
    of its starts uniformly. valid: [T, E] `sample_weights`.

    DrQ-v2 stores an episode when it ends and evicts whole episodes, so the episodes drawn are
    the finished ones, once at least one per env has finished (before: every episode, running
    ones too), and, once the ring has wrapped, not the one each env's oldest row belongs to (it
    has lost its first rows), unless no other is left."""
    k_episode, k_step = jax.random.split(key)
    num_envs = state.frames.shape[1]
    rows = jnp.arange(state.rows)[:, None]
    # An episode's starts are consecutive rows: its head is the one whose row before is none.
    same_before, _ = _same_episode_at(state, rows, jnp.arange(num_envs)[None, :], -1)
    valid = valid > 0
    head = valid & ~(same_before & jnp.roll(valid, 1, axis=0))
    finished = head & (state.episode < state.episodes_started - 1)  # a later episode began
    head = jnp.where(finished.any(axis=0).all(), finished, head)  # once every env finished one
    wrapped = state.size == state.rows
    whole = head & ~(wrapped & (state.episode == state.episode[state.pos]))
    head = jnp.where(whole.any(), whole, head)
    row, env = jnp.divmod(_draw(k_episode, head.reshape(-1), n), num_envs)
    _, last = _episode_span(state, row, env)
    starts = last - _age(state, row)  # every stored row of the episode from the head but its last
    return (row + jax.random.randint(k_step, row.shape, 0, starts)) % state.rows, env


def sample(
    state: ReplayState,
    key: jax.Array,
    batch_size: int,
    *,
    nstep: int,
    gamma: float,
    frame_stack: int,
    same_episode: bool = False,
    by_episode: bool = False,
    skip_positives: bool = True,
) -> Batch:
    """Uniform sample (with replacement) of `batch_size` transitions among the valid starts;
    by_episode=True: an episode uniformly, then a start in it (`_draw_by_episode`).

    same_episode=True also returns TED's same-episode frames (`same_episode_offsets`, which
    takes `skip_positives`). Raises ValueError when called on a replay holding no transition
    (outside `jit`; inside, the trainer checks once before its first update, see
    `check_can_sample`).
    """
    k_idx, k_far = jax.random.split(key)
    weights = sample_weights(state, frame_stack)
    if not isinstance(weights, jax.core.Tracer):
        check_can_sample(weights.sum(), 1)
    if by_episode:
        row, env = _draw_by_episode(k_idx, state, weights, batch_size)
    else:
        flat = _draw(k_idx, weights.reshape(-1), batch_size)
        row, env = jnp.divmod(flat, state.frames.shape[1])
    return sample_at(
        state,
        row,
        env,
        nstep=nstep,
        gamma=gamma,
        frame_stack=frame_stack,
        far_key=k_far if same_episode else None,
        skip_positives=skip_positives,
    )


def check_can_sample(transitions, needed: int) -> None:
    """Raise unless every seed's replay holds at least `needed` transitions (host check).

    Sampling an empty replay would divide by zero weights and return garbage silently.
    """
    have = np.atleast_1d(np.asarray(transitions)).astype(int)
    if (have < needed).any():
        raise ValueError(
            f"the replay holds {have.tolist()} sampleable transitions (per seed) but at least "
            f"{needed} are needed to sample; collect more before updating "
            "(raise replay.seed_frames, or lower agent.batch_size; replay.capacity must exceed "
            "envs_per_seed x frame_stack entries, or the ring holds no full stack and its next)"
        )


def num_transitions(state: ReplayState, frame_stack: int) -> np.ndarray:
    """How many transitions can be sampled now (host value; [S] for a replay with a seed axis)."""
    weights = sample_weights if state.frames.ndim == 5 else jax.vmap(sample_weights, (0, None))
    return np.asarray(weights(state, frame_stack).sum((-2, -1)))
