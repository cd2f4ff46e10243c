"""Where a run's arrays live: the mesh its lanes are split over, and each process's share of them
(`Hosts`).

Several devices (`config.devices`): the seeds axis of every array the loop carries (agent,
replay, env states and timesteps, returns) is split over a mesh of N local devices, axis
"seeds", each device holding S / N seeds; act, learn and add run per device
(`dear_jax/programs.py`), physics and the env's device half stay where their seeds live, and
one render pool on the host feeds them all. `devices=1` keeps arrays uncommitted on the default
device, with no mesh.

Several devices per lane (`config.devices_per_seed` = k > 1, one process): the mesh is 2-D,
("seeds", "batch"), N / k devices by k. Each lane lives whole on each of its k devices (every
array is replicated over "batch"); each device draws its own k-th of the lane's batch and the
update averages the gradients over "batch" (`lax.pmean`; TED's classifier counts its valid pairs
over it), so the k replicas take the whole batch's step and their parameters stay equal.

Several processes (`jax.distributed`): the mesh spans every process's `config.devices` devices
and the loop's arrays are global; each process steps, renders, logs and stores its own block of
lanes (`Hosts`), and every decision that issues a program is made from values all processes
agree on (`Hosts.agree`), so all run the same programs in the same order.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

BATCH = "batch"  # the mesh axis a lane's batch is split over (devices_per_seed > 1)


def num_devices(devices, seeds: int, available: int, per_seed: int = 1) -> int:
    """`config.devices` ("all" or an int) as a device count, refused unless it fits the host's
    `available` devices, splits into groups of `per_seed` (`config.devices_per_seed`) and the
    groups split the `seeds` evenly (a sweep's lanes: seeds x settings)."""
    if not isinstance(per_seed, int) or isinstance(per_seed, bool) or per_seed < 1:
        raise ValueError(f"devices_per_seed must be an int >= 1, got {per_seed!r}")
    if devices == "all":
        n = available
    elif isinstance(devices, int) and not isinstance(devices, bool) and devices >= 1:
        n = devices
    else:
        raise ValueError(f"devices must be 'all' or an int >= 1, got {devices!r}")
    if n > available:
        counts = "1" if available == 1 else f"1 to {available}"
        raise ValueError(
            f"devices={devices} but {available} {jax.default_backend()} device(s) exist here; "
            f"valid: {counts}, or 'all'"
        )
    if n % per_seed:
        raise ValueError(
            f"devices={devices} ({n} devices) cannot be split into groups of "
            f"devices_per_seed={per_seed}; make devices a multiple of {per_seed}"
        )
    groups = n // per_seed  # the lanes' blocks
    if seeds % groups:
        valid = [g * per_seed for g in range(1, available // per_seed + 1) if seeds % g == 0]
        grouped = f" in groups of devices_per_seed={per_seed}" if per_seed > 1 else ""
        raise ValueError(
            f"seeds={seeds} cannot be split evenly over devices={devices} ({n} devices{grouped}); "
            f"valid devices for {seeds} seeds: {', '.join(map(str, valid))}; or make seeds a "
            f"multiple of {groups}"
        )
    return n


def seed_mesh(devices, num_lanes: int, per_seed: int = 1) -> Mesh | None:
    """The mesh ("seeds") of the first `devices` (`config.devices`) local devices; None for
    one device. With several processes, of the first `devices` devices of every process, in
    process order: process p holds the p-th block of the `num_lanes` lanes. With `per_seed`
    (`config.devices_per_seed`) > 1, the 2-D mesh ("seeds", "batch") of those devices."""
    hosts = jax.process_count()
    per_host = lanes_per_host(num_lanes, hosts)
    n = num_devices(devices, per_host, jax.local_device_count(), per_seed)
    if per_seed > 1:
        if hosts > 1:
            raise ValueError(
                f"devices_per_seed={per_seed} needs one process; this run has {hosts} "
                "(split lanes over processes with devices_per_seed=1)"
            )
        grid = np.array(jax.local_devices()[:n]).reshape(n // per_seed, per_seed)
        return Mesh(grid, ("seeds", BATCH))
    if hosts == 1:
        return None if n == 1 else Mesh(np.array(jax.local_devices()[:n]), ("seeds",))
    devices = [[d for d in jax.devices() if d.process_index == p][:n] for p in range(hosts)]
    return Mesh(np.array(sum(devices, [])), ("seeds",))


def lanes_per_host(num_lanes: int, hosts: int) -> int:
    """Lanes per process, refused unless the processes split them evenly."""
    if num_lanes % hosts:
        valid = [h for h in range(1, num_lanes + 1) if num_lanes % h == 0]
        raise ValueError(
            f"{num_lanes} lanes (seeds x sweep settings) cannot be split evenly over {hosts} "
            f"processes; valid process counts: {', '.join(map(str, valid))}; or make the lanes "
            f"a multiple of {hosts}"
        )
    return num_lanes // hosts


def batch_split(mesh: Mesh | None) -> int:
    """The devices each lane's batch is split over (1: none)."""
    return 1 if mesh is None else mesh.shape.get(BATCH, 1)


def seed_groups(mesh: Mesh | None) -> int:
    """The blocks the lanes are split into: one per device, or per group of `batch_split`."""
    return 1 if mesh is None else mesh.shape["seeds"]


def seed_sharding(mesh: Mesh | None) -> NamedSharding | None:
    """Arrays with a leading seeds axis split over `mesh` (None: no mesh, the default device)."""
    return None if mesh is None else NamedSharding(mesh, P("seeds"))


class Hosts:
    """This process's share of a run's arrays. One process: every array is whole here and the
    methods do nothing. Several (`jax.distributed`): the loop's arrays are global (split over
    `mesh`, every process's devices), while this process's envs, logs and replay files hold its
    block of lanes (`lanes`) on its own devices (`local`, the env's sharding); the methods move
    between the two without copies, and `agree` is the one place processes exchange values."""

    def __init__(self, mesh: Mesh | None, num_lanes: int):
        self.count, self.index = jax.process_count(), jax.process_index()
        self.mesh = mesh
        per_host = num_lanes // self.count
        self.lanes = range(self.index * per_host, (self.index + 1) * per_host)
        self.local = seed_sharding(mesh)
        if self.count > 1:
            mine = [d for d in mesh.devices if d.process_index == self.index]
            self.local = NamedSharding(Mesh(np.array(mine), ("seeds",)), P("seeds"))

    @property
    def multi(self) -> bool:
        return self.count > 1

    @property
    def num_devices(self) -> int:
        """The devices this process trains on."""
        return 1 if self.local is None else len(self.local.device_set)

    def _shards(self, x) -> list:
        """x's shards on this process's devices, in mesh order."""
        by_device = {s.device: s.data for s in x.addressable_shards}
        return [by_device[d] for d in self.local.mesh.devices]

    def to_global(self, tree):
        """This process's block [S / P, ...] (on `local`) -> the run's array [S, ...]; 0-d
        leaves, which must be the same on every process -> replicated."""
        if not self.multi:
            return tree

        def one(x):
            if x.ndim == 0:
                return self.place(x, NamedSharding(self.mesh, P()))
            if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
                data = one(jax.random.key_data(x))
                return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
            shape = (x.shape[0] * self.count, *x.shape[1:])
            return jax.make_array_from_single_device_arrays(
                shape, seed_sharding(self.mesh), self._shards(x)
            )

        return jax.tree.map(one, tree)

    def to_local(self, tree):
        """The run's arrays [S, ...] -> this process's block [S / P, ...] on `local`; replicated
        0-d leaves -> uncommitted arrays here."""
        if not self.multi:
            return tree

        def one(x):
            if x.ndim == 0:
                return uncommitted(x.addressable_data(0))
            if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
                data = one(jax.random.key_data(x))
                return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
            shape = (x.shape[0] // self.count, *x.shape[1:])
            return jax.make_array_from_single_device_arrays(shape, self.local, self._shards(x))

        return jax.tree.map(one, tree)

    def read(self, x) -> np.ndarray:
        """This process's block of a [S, ...] array, on the host."""
        if not self.multi:
            return np.asarray(x)
        return np.concatenate([np.asarray(a) for a in self._shards(x)])

    def place(self, x, sharding):
        """A value every process holds whole and alike, placed over the run's devices."""
        if not self.multi:
            return jax.device_put(x, sharding)
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            data = self.place(jax.random.key_data(x), sharding)
            return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    def place_local(self, x: np.ndarray):
        """This process's block [S / P, ...] of host values -> the run's array [S, ...]."""
        shape = (x.shape[0] * self.count, *x.shape[1:])
        return jax.make_array_from_process_local_data(seed_sharding(self.mesh), x, shape)

    def env_key(self, key):
        """A key of the loop (on every device) as this process's envs take it: here, and
        folded with the process index, so processes draw different episode starts."""
        if not self.multi:
            return key
        return jax.random.fold_in(self.to_local(key), self.index)

    def agree(self, values) -> np.ndarray:
        """[processes, k]: every process's `values` (k numbers), the same on every process."""
        values = np.asarray(values, np.int64)
        if not self.multi:
            return values[None]
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(values)).reshape(self.count, -1)


def uncommitted(x):
    """`x` as a fresh run has it: a device array not committed to a device. jit compiles
    separately for committed arguments (orbax restores those), so a resumed run would otherwise
    compile every program of the loop twice."""
    if not isinstance(x, jax.Array):
        return x
    if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
        data = jnp.asarray(np.asarray(jax.random.key_data(x)))
        return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
    return jnp.asarray(np.asarray(x))
