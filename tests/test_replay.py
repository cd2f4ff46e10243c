"""The device replay against a plain Python reference: stacks, n-step returns, episode ends, wrap-around."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dear_jax import replay

FRAME = (2, 2, 1)  # tiny frames: the value identifies (env, global step)


def _frame_value(env, g):
    return (g * 3 + env * 101) % 251


def _rollout(num_envs, steps, seed):
    """Random episodes per env with random lengths (some of length 1 transition)."""
    rng = np.random.default_rng(seed)
    logs = []
    first = np.ones(num_envs, bool)
    remaining = rng.integers(1, 6, num_envs)
    for g in range(steps):
        step = {
            "frame": np.stack(
                [np.full(FRAME, _frame_value(e, g), np.uint8) for e in range(num_envs)]
            ),
            "mask": np.stack([np.full(FRAME[:2], (g + e) % 2, np.uint8) for e in range(num_envs)]),
            "action": rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32),
            "reward": rng.uniform(0, 1, num_envs).astype(np.float32),
            "discount": (rng.uniform(size=num_envs) > 0.2).astype(np.float32),
            "first": first.copy(),
        }
        logs.append(step)
        last = remaining == 0
        remaining = np.where(last, rng.integers(1, 6, num_envs), remaining - 1)
        first = last
    return logs


def _filled(logs, capacity):
    """A replay of `capacity` entries holding the rollout `logs`, row by row."""
    state = replay.init(capacity, len(logs[0]["first"]), FRAME, 2)
    add = jax.jit(replay.add)
    for s in logs:
        state = add(
            state, s["frame"], s["mask"], s["action"], s["reward"], s["discount"], s["first"]
        )
    return state


def _reference(logs, rows, e, g, nstep, gamma, k_stack):
    """Plain Python transition starting at global step g of env e, or None if not a valid start."""
    total = len(logs)
    oldest = max(0, total - rows)
    ep = np.cumsum([s["first"][e] for s in logs]) - 1
    if g < oldest or g + 1 >= total or ep[g + 1] != ep[g]:
        return None
    if total > rows and g - oldest < k_stack - 1:
        return None

    def stack(i):
        # frames before the episode start (or before the oldest stored row) repeat the first one
        start = min(j for j in range(oldest, i + 1) if ep[j] == ep[i])
        return [max(i - k, start) for k in range(k_stack - 1, -1, -1)]

    reward, discount, nxt = 0.0, 1.0, g
    for k in range(1, nstep + 1):
        j = g + k
        if j >= total or ep[j] != ep[g]:
            break
        reward += discount * logs[j]["reward"][e]
        discount *= gamma * logs[j]["discount"][e]
        nxt = j
    return {
        "obs": [_frame_value(e, j) for j in stack(g)],
        "next_obs": [_frame_value(e, j) for j in stack(nxt)],
        "mask": [logs[j]["mask"][e][0, 0] for j in stack(g)],
        "action": logs[g + 1]["action"][e],
        "reward": reward,
        "discount": discount,
    }


@pytest.mark.parametrize("steps,capacity", [(9, 30), (23, 30), (61, 30)])
def test_sample_matches_python_reference(steps, capacity):
    num_envs, nstep, gamma, k = 3, 3, 0.9, 3
    logs = _rollout(num_envs, steps, seed=steps)
    state = _filled(logs, capacity)
    rows = state.rows
    total = len(logs)
    starts, expected = [], []
    for g in range(max(0, total - rows), total):
        for e in range(num_envs):
            ref = _reference(logs, rows, e, g, nstep, gamma, k)
            if ref is not None:
                starts.append((g % rows, e))
                expected.append(ref)
    weights = np.asarray(replay.sample_weights(state, k))
    assert weights.sum() == len(starts)
    for row, e in starts:
        assert weights[row, e] == 1.0
    row = jnp.array([s[0] for s in starts])
    env = jnp.array([s[1] for s in starts])
    batch = replay.sample_at(state, row, env, nstep=nstep, gamma=gamma, frame_stack=k)
    for i, ref in enumerate(expected):
        np.testing.assert_array_equal(batch.obs[i, 0, 0], ref["obs"])
        np.testing.assert_array_equal(batch.next_obs[i, 0, 0], ref["next_obs"])
        np.testing.assert_array_equal(batch.mask[i, 0, 0], ref["mask"])
        np.testing.assert_allclose(batch.action[i], ref["action"], rtol=1e-6)
        np.testing.assert_allclose(batch.reward[i], ref["reward"], rtol=1e-5)
        np.testing.assert_allclose(batch.discount[i], ref["discount"], rtol=1e-5)


def test_uniform_sample_only_returns_valid_starts_and_same_episode_negatives():
    num_envs = 2
    logs = _rollout(num_envs, 40, seed=5)
    state = _filled(logs, 24)
    sample = jax.jit(
        functools.partial(
            replay.sample, batch_size=512, nstep=2, gamma=0.99, frame_stack=3, same_episode=True
        )
    )
    batch = sample(state, jax.random.key(0))
    values = {}  # frame value -> (env, global step)
    for g in range(len(logs)):
        for e in range(num_envs):
            values[_frame_value(e, g)] = (e, g)
    ep = {e: np.cumsum([s["first"][e] for s in logs]) - 1 for e in range(num_envs)}
    valid_pairs = 0
    for i in range(512):
        e, g = values[int(batch.obs[i, 0, 0, -1])]
        ref = _reference(logs, state.rows, e, g, 2, 0.99, 3)
        assert ref is not None
        np.testing.assert_allclose(batch.reward[i], ref["reward"], rtol=1e-5)
        if batch.far_valid[i]:
            e2, g2 = values[int(batch.far_obs[i, 0, 0, -1])]
            assert e2 == e and ep[e][g2] == ep[e][g] and (g2 - g <= -2 or g2 - g > 2)
            valid_pairs += 1
    assert valid_pairs > 100


def test_vmapped_over_seeds():
    s, num_envs = 3, 2
    state = replay.init(10, num_envs, FRAME, 2, leading=(s,))
    frame = jnp.arange(s * num_envs * 4, dtype=jnp.uint8).reshape(s, num_envs, *FRAME)
    state = jax.vmap(replay.add)(
        state,
        frame,
        frame[..., 0],
        jnp.zeros((s, num_envs, 2)),
        jnp.ones((s, num_envs)),
        jnp.ones((s, num_envs)),
        jnp.ones((s, num_envs), bool),
    )
    assert state.frames.shape == (s, 5, num_envs, *FRAME)
    np.testing.assert_array_equal(state.frames[:, 0], frame)
    np.testing.assert_array_equal(state.pos, [1, 1, 1])
    # Seeds of their own rows (frames, rewards, episode starts): each seed's vmapped batch is its
    # own buffer's batch under its key.
    rng = np.random.default_rng(0)
    for row in range(1, 7):
        first = np.zeros((s, num_envs), bool)
        first[1, 0] = row == 3  # seed 1's env 0 starts an episode here
        state = jax.vmap(replay.add)(
            state,
            jnp.asarray(rng.integers(0, 256, (s, num_envs, *FRAME)), jnp.uint8),
            jnp.zeros((s, num_envs, *FRAME[:2]), jnp.uint8),
            jnp.asarray(rng.normal(size=(s, num_envs, 2)), jnp.float32),
            jnp.asarray(rng.normal(size=(s, num_envs)), jnp.float32),
            jnp.ones((s, num_envs)),
            jnp.asarray(first),
        )
    sample = functools.partial(replay.sample, batch_size=8, nstep=2, gamma=0.9, frame_stack=3)
    keys = jax.random.split(jax.random.key(1), s)
    together = jax.vmap(sample)(state, keys)
    for i in range(s):
        alone = sample(jax.tree.map(lambda x, i=i: x[i], state), keys[i])
        for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(together)):
            np.testing.assert_array_equal(a, b[i])
    assert not np.array_equal(together.obs[0], together.obs[1])


def test_capacity_check_says_how_much_is_needed():
    need = replay.replay_bytes(5, 250_000, (84, 84, 3), 6)
    assert need == 5 * 250_000 * (84 * 84 * 3 + 84 * 84 + 24 + 12)
    with pytest.raises(MemoryError, match=r"needs 32\.90 GiB .* replay.capacity to at most 48,633"):
        replay.check_fits(5, 250_000, (84, 84, 3), 6, available=8 * 2**30)
    assert replay.check_fits(1, 1000, (84, 84, 3), 6, available=8 * 2**30) == need // 1250
    # A sweep's buffers are its lanes: the message counts and remedies those.
    sweep = "lanes (2 seeds x 3 settings)"
    with pytest.raises(
        MemoryError, match=r"for 6 lanes \(2 seeds x 3 settings\) .* seeds or settings$"
    ):
        replay.check_fits(6, 250_000, (84, 84, 3), 6, available=8 * 2**30, lanes=sweep)


def _one_env_replay(episode_lengths, rows):
    """One env whose episodes have the given numbers of entries; frame value = global step."""
    state = replay.init(rows, 1, FRAME, 2)
    g = 0
    for length in episode_lengths:
        for i in range(length):
            state = replay.add(
                state,
                jnp.full((1, *FRAME), g, jnp.uint8),
                jnp.zeros((1, *FRAME[:2]), jnp.uint8),
                jnp.zeros((1, 2)),
                jnp.zeros(1),
                jnp.ones(1),
                jnp.array([i == 0]),
            )
            g += 1
    return state


@pytest.mark.parametrize(
    "lengths, rows, t, nstep, skip_positives, expected",
    [
        # t = 6 in an episode of entries 3..14: any of 3..14 but 5, 6, 7.
        ((3, 12, 4), 32, 6, 1, True, [*range(3, 5), *range(8, 15)]),
        # With 3-step positives (6, 6+n'), n' <= 3: 7..9 are excluded as well ...
        ((3, 12, 4), 32, 6, 3, True, [*range(3, 5), *range(10, 15)]),
        # ... but not as TED's code draws them (ted_form "reference_code"): t+-1 only.
        ((3, 12, 4), 32, 6, 3, False, [*range(3, 5), *range(8, 15)]),
        # The ring (12 rows) holds steps 7..18: episode 3..14 keeps 7..14; t = 8 excludes 7..9.
        ((3, 12, 4), 12, 8, 1, True, [*range(10, 15)]),
        # An episode of two entries has no step at distance >= 2.
        ((2, 5), 16, 0, 1, True, []),
    ],
)
def test_same_episode_negatives_are_uniform_over_the_episode_but_t_and_neighbours(
    lengths, rows, t, nstep, skip_positives, expected
):
    state = _one_env_replay(lengths, rows)
    draws = 4000
    row = jnp.full((draws,), t % rows)
    env = jnp.zeros((draws,), jnp.int32)
    keys = jax.random.split(jax.random.key(0), draws)
    draw = functools.partial(
        replay.same_episode_offsets, nstep=nstep, skip_positives=skip_positives
    )
    offset, valid = jax.jit(jax.vmap(draw, in_axes=(None, 0, 0, 0)))(
        state, row[:, None], env[:, None], keys
    )
    offset, valid = np.asarray(offset[:, 0]), np.asarray(valid[:, 0])
    if not expected:
        assert not valid.any()
        return
    assert valid.all()
    steps, counts = np.unique(t + offset, return_counts=True)
    assert steps.tolist() == expected
    # Uniform: each count within 5 standard deviations of draws / len(expected).
    p = 1 / len(expected)
    assert np.all(np.abs(counts - draws * p) < 5 * np.sqrt(draws * p * (1 - p))), counts


def test_same_episode_frames_are_whole_stacks_after_the_ring_wraps():
    """One episode of 30 steps in a ring of 12 rows (steps 18..29): TED's same-episode frames,
    like the observations, are stacks of 3 consecutive stored frames, never the oldest stored
    frame repeated in place of the overwritten ones."""
    state = replay.init(12, 1, (2, 2, 1), 2)
    for g in range(30):
        state = replay.add(
            state,
            jnp.full((1, 2, 2, 1), g, jnp.uint8),
            jnp.zeros((1, 2, 2), jnp.uint8),
            jnp.zeros((1, 2)),
            jnp.zeros(1),
            jnp.ones(1),
            jnp.array([g == 0]),
        )
    sample = functools.partial(replay.sample, nstep=1, gamma=0.99, frame_stack=3, same_episode=True)
    batch = jax.jit(sample, static_argnums=2)(state, jax.random.key(0), 4000)
    far = np.asarray(batch.far_obs[:, 0, 0])[np.asarray(batch.far_valid) > 0].astype(int)
    assert len(far) > 3000 and far.min() >= 18
    np.testing.assert_array_equal(far[:, 1:] - far[:, :-1], 1)  # consecutive frames
    assert far[:, 0].min() == 18  # the oldest whole stack (18, 19, 20) is drawn


def _assert_drawn_by_episode(state, want, key, draws=24_000):
    """Starts drawn by episode (frame_stack 1: a frame's value names its start) are exactly
    those of `want`, each as often as its probability there (within 5 standard deviations)."""
    sample = functools.partial(replay.sample, nstep=1, gamma=0.99, frame_stack=1, by_episode=True)
    batch = jax.jit(sample, static_argnums=2)(state, jax.random.key(key), draws)
    starts, counts = np.unique(np.asarray(batch.obs[:, 0, 0, 0]), return_counts=True)
    assert starts.tolist() == sorted(want)
    p = np.array([want[s] for s in starts.tolist()])
    assert np.all(np.abs(counts - draws * p) < 5 * np.sqrt(draws * p * (1 - p))), counts


@pytest.mark.parametrize(
    "lengths, rows, want",
    [
        # Episodes of 3, 12, 5 entries finished (2, 11, 4 starts), the 4th still running:
        # each finished one a third of the draws, spread evenly over its starts.
        ((3, 12, 5, 4), 32, {**dict.fromkeys(range(0, 2), 1 / 6),
                             **dict.fromkeys(range(3, 14), 1 / 33),
                             **dict.fromkeys(range(15, 19), 1 / 12)}),
        # The ring of 12 rows holds steps 12..23: the second episode, which lost its first
        # rows, is left out, as DrQ-v2 evicts whole episodes.
        ((3, 12, 5, 4), 12, dict.fromkeys(range(15, 19), 1 / 4)),
        # ... unless no other is left: the ring of 6 rows holds steps 10..14 of the second
        # and the one entry of the third (no start).
        ((3, 12, 1), 6, dict.fromkeys(range(10, 14), 1 / 4)),
        # No episode has finished: the running one's starts alike.
        ((7,), 32, dict.fromkeys(range(0, 6), 1 / 6)),
    ],
)  # fmt: skip
def test_episode_sampling_draws_a_finished_episode_then_a_start_in_it(lengths, rows, want):
    """replay.sampling "episode" (DrQ-v2's replay): the frequency of a start is 1 / (episodes x
    its episode's starts), where uniform sampling gives every start the same."""
    state = _one_env_replay(lengths, rows)
    _assert_drawn_by_episode(state, want, key=0)


def test_episode_sampling_over_envs_returns_valid_transitions_of_finished_episodes():
    """Over several envs, every draw is a valid transition (the reference's values) of a
    finished episode, and the finished episodes of all envs are drawn about equally often."""
    num_envs = 3
    logs = _rollout(num_envs, 60, seed=11)
    state = _filled(logs, 48)
    draws = 30_000
    batch = jax.jit(
        functools.partial(replay.sample, nstep=2, gamma=0.9, frame_stack=3, by_episode=True),
        static_argnums=2,
    )(state, jax.random.key(3), draws)
    values = {_frame_value(e, g): (e, g) for g in range(len(logs)) for e in range(num_envs)}
    ep = {e: np.cumsum([s["first"][e] for s in logs]) - 1 for e in range(num_envs)}
    seen = {}
    for i in range(draws):
        e, g = values[int(batch.obs[i, 0, 0, -1])]
        if i < 300:
            ref = _reference(logs, state.rows, e, g, 2, 0.9, 3)
            assert ref is not None
            np.testing.assert_allclose(batch.reward[i], ref["reward"], rtol=1e-5)
        assert ep[e][g] < ep[e][-1], "a draw from an episode that has not finished"
        seen[e, ep[e][g]] = seen.get((e, ep[e][g]), 0) + 1
    # Every finished episode with a start, but the one of each env's oldest stored row, which
    # the ring has cut (the rollout has many episodes per env and has wrapped the ring).
    oldest = len(logs) - state.rows
    assert oldest > 0
    with_start = {
        (e, ep[e][g])
        for e in range(num_envs)
        for g in range(len(logs))
        if ep[e][oldest] < ep[e][g] < ep[e][-1]
        and _reference(logs, state.rows, e, g, 2, 0.9, 3) is not None
    }
    assert set(seen) == with_start
    counts = np.array(list(seen.values()))
    p = 1 / len(with_start)
    assert np.all(np.abs(counts - draws * p) < 5 * np.sqrt(draws * p * (1 - p))), counts


@pytest.mark.parametrize(
    "env0_starts, want",
    [
        # One finished episode (env 0's first, 3 entries) beside two running ones (env 0's
        # second, 5 entries; env 1's, 8): all three drawn, each a third of the draws.
        ((0, 3), {0: 1 / 6, 1: 1 / 6, **dict.fromkeys(range(3, 7), 1 / 12)}),
        # Env 0 has finished two (as many as there are envs), env 1 none: all four still drawn,
        # env 1's running one too, each a quarter.
        ((0, 3, 6), {0: 1 / 8, 1: 1 / 8, 3: 1 / 8, 4: 1 / 8, 6: 1 / 4}),
    ],
)
def test_episode_sampling_draws_running_episodes_until_each_env_has_finished_one(env0_starts, want):
    """Two envs over 8 steps, env 1 in one running episode: until each env has finished an
    episode, every episode is drawn, running ones too, evenly over its starts."""
    state = replay.init(32, 2, FRAME, 2)
    for g in range(8):
        state = replay.add(
            state,
            jnp.stack([jnp.full(FRAME, g, jnp.uint8), jnp.full(FRAME, 100 + g, jnp.uint8)]),
            jnp.zeros((2, *FRAME[:2]), jnp.uint8),
            jnp.zeros((2, 2)),
            jnp.zeros(2),
            jnp.ones(2),
            jnp.array([g in env0_starts, g == 0]),
        )
    episodes = len(env0_starts) + 1
    want = {**want, **dict.fromkeys(range(100, 107), 1 / (7 * episodes))}
    _assert_drawn_by_episode(state, want, key=4)


def test_sampling_an_empty_replay_raises():
    state = replay.init(8, 2, FRAME, 2)
    with pytest.raises(ValueError, match="holds \\[0\\] sampleable transitions"):
        replay.sample(state, jax.random.key(0), 4, nstep=1, gamma=0.99, frame_stack=3)


def test_draws_are_uniform_over_valid_entries_without_a_loop():
    """The sampler returns only valid entries, each about equally often, every one reachable
    (the search's edges included), the same numbers for a seed alone or vmapped with others,
    and its program has no loop (a GPU would sync with the host at every step of one)."""
    valid = (jax.random.uniform(jax.random.key(0), (301,)) > 0.4).astype(jnp.float32)
    valid = valid.at[0].set(1).at[-1].set(1)
    draws = np.asarray(replay._draw(jax.random.key(1), valid, 200_000))
    counts = np.bincount(draws, minlength=301)
    assert (counts[np.asarray(valid) == 0] == 0).all()
    expected = 200_000 / int(valid.sum())
    assert np.abs(counts[np.asarray(valid) == 1] - expected).max() < 6 * np.sqrt(expected)
    for n in (1, 2, 5):
        assert set(np.asarray(replay._draw(jax.random.key(n), jnp.ones(n), 500))) == set(range(n))
    keys = jax.random.split(jax.random.key(2), 3)
    rows = jnp.stack([valid, jnp.roll(valid, 7), jnp.ones(301)])
    vmapped = jax.vmap(replay._draw, (0, 0, None))(keys, rows, 64)
    for k, row, got in zip(keys, rows, vmapped, strict=True):
        np.testing.assert_array_equal(replay._draw(k, row, 64), got)
    jaxpr = str(jax.make_jaxpr(replay._draw, static_argnums=2)(jax.random.key(0), valid, 256))
    assert "while" not in jaxpr and "scan" not in jaxpr
