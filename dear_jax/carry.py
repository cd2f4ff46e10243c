"""What the training loop carries from one step to the next: agent, replay, envs mid-episode,
keys, counters and the sums of the next log row. A checkpoint holds all of it (`Carry.tree`: the
arrays; `Carry.extra`: host values), so a resumed run continues exactly as the uninterrupted
one: same updates, same parameters bit for bit, same log rows."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from dear_jax.devices import Hosts


def _is_host(x) -> bool:
    return isinstance(x, (np.ndarray, np.generic))


def _to_host(x) -> np.ndarray:
    if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
        x = jax.random.key_data(x)
    return np.asarray(x)


def _like(template, value):
    """`value`, a host copy of a leaf like `template` (`_to_host`), as `template` is."""
    if _is_host(template):
        return value
    if jnp.issubdtype(template.dtype, jax.dtypes.prng_key):
        return jax.random.wrap_key_data(jnp.asarray(value), impl=jax.random.key_impl(template))
    return jnp.asarray(value)


class Carry:
    """The loop's values: `agent`, `buffer` (the replay), `key`, `state` and `ts` (the envs'
    state and timesteps), `returns` (of the episodes under way), `counters`, `lv` (loop
    variables), `metric_sum` and `episode_returns` (the next train row's sums)."""

    def __init__(
        self, hosts: Hosts, *, agent, buffer, key, state, ts, returns, seed_frames, log_every
    ):
        self.hosts = hosts
        self.agent, self.buffer, self.key = agent, buffer, key
        self.state, self.ts, self.returns = state, ts, returns
        self.counters = {
            "frame": 0,
            "iteration": 0,
            "episode": 0,
            "updates": 0,
            "rows": 0,  # rows added to the replay (its row r lives in ring row r % T)
            "wall_s": 0.0,
        }
        self.lv = {  # loop variables carried between steps
            "steps_owed": 0.0,  # agent steps per seed not yet matched by updates
            "seed_frames": seed_frames,  # the frame updates start at
            "env_steps": 0,  # agent steps taken, summed over all seeds' envs
            "episodes_ended": 0,  # episodes ended, summed over all seeds' envs
            "metric_count": 0,
            "next_log": log_every,
            "last_log_frame": 0,
            "next_eval": 0,  # as DrQ-v2: every curve starts at the untrained policy
            "last_eval_frame": -1,
        }
        self.metric_sum = None  # train metrics summed since the last log row
        # Per step that ended episodes: their returns summed per seed ([S], on the device until
        # read) and their count per seed of this process ([S], host); `ended_episodes` reads them.
        self.episode_returns = []
        self.episodes_pending = False  # an episode ended (on any process) since the last row

    def add_ended(self, returns, ended: np.ndarray) -> None:
        """Keep a step's ended episodes for the next train row: `returns` [S] (on the device:
        read only when a row or a checkpoint needs it) the sums of their returns per seed
        (programs.accumulate), `ended` [S, E] this process's envs that ended them."""
        if ended.any():
            self.episode_returns.append((returns, ended.sum(1)))

    def ended_episodes(self) -> list[np.ndarray]:
        """[2, S] per step that ended episodes: their returns summed and their count, for each
        seed of this process."""
        self.episode_returns = [
            (r if isinstance(r, np.ndarray) else self.hosts.read(r), n)
            for r, n in self.episode_returns
        ]
        return [np.stack(pair) for pair in self.episode_returns]

    def _saved_on_host(self, x) -> bool:
        """Env state leaves saved with this process's host values: numpy ones and, with several
        processes, the env's key (each process's envs have their own)."""
        return _is_host(x) or (self.hosts.multi and x.ndim == 0)

    def tree(self) -> dict:
        """The checkpoint's arrays (and, on restoring, the template of where they go)."""
        b = self.buffer
        return {
            "agent": self.agent,
            "key": self.key,
            "env": self.hosts.to_global(
                [x for x in jax.tree.leaves(self.state) if not self._saved_on_host(x)]
            ),
            "ts": self.ts,
            "returns": self.returns,
            "replay": {"episodes_started": b.episodes_started, "pos": b.pos, "size": b.size},
        }

    def extra(self, *, env_rng: dict, eval_env_rng: dict, replay_on_disk: bool) -> dict:
        """The checkpoint's host values; `env_rng` and `eval_env_rng`: the envs' host states."""
        return {
            "counters": dict(self.counters),
            "loop": dict(self.lv),
            "metric_sum": (
                None
                if self.metric_sum is None
                else {k: self.hosts.read(v) for k, v in self.metric_sum.items()}
            ),
            "episode_returns": self.ended_episodes(),
            "env_host": [
                _to_host(x) for x in jax.tree.leaves(self.state) if self._saved_on_host(x)
            ],
            "env_rng": env_rng,
            "eval_env_rng": eval_env_rng,
            "replay_on_disk": replay_on_disk,
            "processes": self.hosts.count,
        }

    def load(self, restored: dict, extra: dict) -> None:
        """Take a checkpoint's values (`restored`: `tree`'s arrays as restored, `extra`); the
        replay's contents and the envs' host states are the caller's."""
        self.agent, self.key = restored["agent"], restored["key"]
        self.ts, self.returns = restored["ts"], restored["returns"]
        leaves, treedef = jax.tree.flatten(self.state)
        device = iter(self.hosts.to_local(restored["env"]))
        host = iter(extra["env_host"])
        self.state = treedef.unflatten(
            [_like(x, next(host)) if self._saved_on_host(x) else next(device) for x in leaves]
        )

    def load_host_values(self, extra: dict, eval_every_frames: int) -> None:
        """Take a checkpoint's counters, loop variables and sums (`extra`)."""
        self.counters = extra["counters"]
        self.lv.update(extra["loop"])
        frame = self.counters["frame"]
        self.lv["last_log_frame"] = frame  # the first rate after a resume counts from here
        if self.lv["next_eval"] > frame:  # none pending: follow this run's eval interval
            self.lv["next_eval"] = (frame // eval_every_frames + 1) * eval_every_frames
        if extra["metric_sum"] is not None:
            self.metric_sum = {
                k: self.hosts.place_local(v) if self.hosts.multi else jnp.asarray(v)
                for k, v in extra["metric_sum"].items()
            }
        self.episode_returns = [tuple(np.asarray(r)) for r in extra["episode_returns"]]
        self.episodes_pending = bool(self.hosts.agree([len(self.episode_returns)]).any())
