"""Lanes: the settings x seeds that one run trains side by side in one compiled program.

A run trains `seeds` seeds of one setting, or, with a sweep, every combination of the swept
values crossed with the seeds:

    python run.py --config paper.py:walker,dear --config.sweep.beta=-1,0,1,10,100

trains 5 x 3 = 15 lanes. A sweep can only vary the per-seed numbers of the update (the fields of
`update.HParams`, taken from `config.agent`): they are arrays with a lane axis in the compiled
program, so every lane runs the same code with its own weights. Lane i is setting i // seeds and
seed i % seeds; lanes of the same seed start from the same parameters (paired comparisons). Each
lane logs under its own folder, named by its settings ("beta=-1_seed_0"; "seed_0" without a
sweep), with its own config.json.

No jax here: run.py checks the config before the slow imports.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import pathlib

from ml_collections import ConfigDict

# The fields of update.HParams (tests/test_lanes.py checks they match): numbers each lane of the
# compiled update can hold its own value of.
SWEEPABLE = (
    "alpha",
    "beta",
    "recon_weight",
    "ted_weight",
    "tau",
    "stddev_clip",
    "std_init",
    "std_final",
    "std_steps",
    "explore_steps",
)
# The methods whose losses read a weight; sweeping it for another method changes nothing.
USED_BY = {
    "alpha": ("dear", "sear"),
    "beta": ("dear",),
    "recon_weight": ("sear",),
    "ted_weight": ("ted",),
}


def default_sweep() -> ConfigDict:
    """configs/base.py's `sweep`: every sweepable key, empty (not swept)."""
    return ConfigDict(dict.fromkeys(SWEEPABLE, ""))


@dataclasses.dataclass(frozen=True)
class Lane:
    index: int  # position on the lane axis of the run's arrays
    seed: int  # seed index: parameters and exploration start from fold_in(key(config.seed), seed)
    settings: tuple[tuple[str, float], ...]  # the swept values of this lane, in sweep order

    @property
    def label(self) -> str:
        """The settings part of the name ("beta=-1"; "" without a sweep)."""
        return "_".join(f"{k}={v:g}" for k, v in self.settings)

    @property
    def name(self) -> str:
        return f"{self.label}_seed_{self.seed}" if self.settings else f"seed_{self.seed}"


def _values(key: str, text) -> tuple[float, ...]:
    if isinstance(text, (int, float)):
        return (float(text),)
    try:
        values = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise ValueError(
            f"sweep.{key}={text!r}: give comma-separated numbers, e.g. --config.sweep.{key}=0,1,10"
        ) from None
    if len(set(values)) != len(values):
        raise ValueError(f"sweep.{key}={text!r} repeats a value")
    return values


def sweep_values(config: ConfigDict) -> dict[str, tuple[float, ...]]:
    """The swept keys and their values; unknown keys and keys the method ignores are refused."""
    sweep = config.get("sweep") or {}
    out = {}
    for key, text in sweep.items():
        if key not in SWEEPABLE:
            raise ValueError(
                f"unknown sweep key {key!r}; a sweep varies the update's per-lane numbers: "
                f"{', '.join(SWEEPABLE)}"
            )
        values = _values(key, text)
        if not values:
            continue
        method = config.agent.method
        if method not in USED_BY.get(key, (method,)):
            raise ValueError(
                f"sweep.{key} has no effect on agent.method={method!r}: only "
                f"{', '.join(USED_BY[key])} use agent.{key}"
            )
        out[key] = values
    return out


def lanes(config: ConfigDict) -> list[Lane]:
    """Every (setting, seed) of the run, in the order of the lane axis."""
    sweep = sweep_values(config)
    settings = [tuple(zip(sweep, combo)) for combo in itertools.product(*sweep.values())]
    return [
        Lane(index=i * config.seeds + s, seed=s, settings=setting)
        for i, setting in enumerate(settings)
        for s in range(config.seeds)
    ]


def num_lanes(config: ConfigDict) -> int:
    return len(lanes(config))


def lane_config(config: ConfigDict, lane: Lane) -> ConfigDict:
    """The config of one lane on its own: its swept values in `agent`, one seed, no sweep."""
    c = ConfigDict(config.to_dict())
    for key, value in lane.settings:
        c.agent[key] = type(c.agent[key])(value)
    c.sweep = default_sweep()
    c.seeds = 1
    c.lane = ConfigDict({"name": lane.name, "seed": lane.seed, "settings": dict(lane.settings)})
    return c


def groups(workdir: str | pathlib.Path) -> dict[str, list[pathlib.Path]]:
    """A run workdir's lane folders grouped by setting ("" without a sweep), in lane order,
    from the config.json the trainer wrote there."""
    workdir = pathlib.Path(workdir)
    path = workdir / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is {workdir} a run's workdir?")
    config = ConfigDict(json.loads(path.read_text()))
    if "seeds" not in config:
        raise ValueError(f"{path} has no 'seeds' field: it is not a config the trainer wrote")
    out: dict[str, list[pathlib.Path]] = {}
    for lane in lanes(config):
        out.setdefault(lane.label, []).append(workdir / lane.name)
    return out


@dataclasses.dataclass
class Pool:
    """The seeds of one experiment's setting, pooled over the run workdirs that trained them
    (other machines, other days): `seeds` holds (workdir, lane folder) per seed, in the order
    the workdirs were given."""

    config: dict  # the first workdir's config.json, its lane's swept values in `agent`, no sweep
    label: str  # the swept numbers that set it apart ("beta=10"; "" where nothing does)
    seeds: list[tuple[pathlib.Path, pathlib.Path]]

    @property
    def workdirs(self) -> list[pathlib.Path]:
        return list(dict.fromkeys(w for w, _ in self.seeds))


def _lane_fields(config: dict, lane: Lane, defaults: dict) -> dict:
    """A lane's flattened config as a run of that setting alone would have it: its swept values
    in `agent` (in the type the field has there), no sweep."""
    fields = {**defaults, **flatten(config)}
    for key in SWEEPABLE:
        fields[f"sweep.{key}"] = ""
    for key, value in lane.settings:
        kind = type(fields.get(f"agent.{key}", value))
        fields[f"agent.{key}"] = kind(value)
    return fields


def _unflatten(fields: dict) -> dict:
    """{"a.b": 1} -> {"a": {"b": 1}}."""
    out: dict = {}
    for dotted, value in fields.items():
        *parents, key = dotted.split(".")
        node = out
        for part in parents:
            node = node.setdefault(part, {})
        node[key] = value
    return out


def pools(workdirs, defaults: dict, ignored: tuple[str, ...]) -> list[Pool]:
    """The workdirs' seeds pooled by experiment: two seeds belong to one experiment when their
    lanes' configs (`_lane_fields`: a sweep's lane as a run of its setting alone) agree on every
    field but `ignored` (the seeds, and what a run may change without changing what it learns),
    a field a config lacks read from `defaults` (the trainer's config of today, flattened, so
    runs logged before a field existed keep its default). So a sweep's beta=10 lanes and runs
    given --config.agent.beta=10 pool, wherever and whenever they ran. A seed is (config.seed,
    lane seed): the same seed of one experiment in two workdirs is refused, since it would be
    counted twice. Each pool's label names its values of the swept numbers (`SWEEPABLE`) in
    which it differs from another pool of the same task and method; "" where none."""
    found: dict[str, tuple[dict, Pool]] = {}
    origin: dict[tuple[str, tuple[int, int]], pathlib.Path] = {}
    for workdir in map(pathlib.Path, workdirs):
        groups(workdir)  # checks the workdir
        config = json.loads((workdir / "config.json").read_text())
        flat = flatten(config)
        for lane in lanes(ConfigDict(config)):
            fields = _lane_fields(config, lane, defaults)
            kept = {k: v for k, v in fields.items() if k not in ignored and k != "seed"}
            key = json.dumps(kept, sort_keys=True, default=str)
            # The config as written, with the lane's values: no default fills a field it lacks.
            own = {k: fields[k] for k in [*flat, *(f"agent.{k}" for k, _ in lane.settings)]}
            _, pool = found.setdefault(key, (kept, Pool(_unflatten(own), "", [])))
            seed = (config.get("seed", 0), lane.seed)
            first = origin.setdefault((key, seed), workdir)
            if first != workdir:
                raise ValueError(
                    f"{first} and {workdir} both trained seed {seed[1]} of config.seed="
                    f"{seed[0]} of the same experiment: the same seed twice. Give each run "
                    "of an experiment its own --config.seed"
                )
            pool.seeds.append((workdir, workdir / lane.name))
    swept = tuple(f"agent.{k}" for k in SWEEPABLE)
    for kept, pool in found.values():
        rest = {k: v for k, v in kept.items() if k not in swept}
        siblings = [other for other, _ in found.values() if rest.items() <= other.items()]
        varying = [k for k in swept if len({json.dumps(s.get(k)) for s in siblings}) > 1]
        pool.label = "_".join(f"{k.removeprefix('agent.')}={kept[k]:g}" for k in varying)
    return [pool for _, pool in found.values()]


def flatten(tree: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1}."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out
