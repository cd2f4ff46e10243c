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
import math
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
    "noise_hold",
)
# The values each sweepable number takes, a swept one and the config's own field alike:
# (least, whether the least is excluded, greatest, whether whole); every one finite.
BOUNDS = {
    **dict.fromkeys(
        ("alpha", "beta", "recon_weight", "ted_weight"), (-math.inf, True, math.inf, False)
    ),
    "tau": (0.0, True, 1.0, False),
    **dict.fromkeys(("stddev_clip", "std_init", "std_final"), (0.0, False, math.inf, False)),
    "std_steps": (1.0, False, math.inf, True),
    "explore_steps": (0.0, False, math.inf, True),
    "noise_hold": (1.0, False, math.inf, True),
}


def check_value(key: str, value: float) -> None:
    """Refuse a value of agent.`key` (a sweepable number) outside `BOUNDS`, naming the valid ones."""
    low, open_low, high, whole = BOUNDS[key]
    above = low < value if open_low else low <= value
    if math.isfinite(value) and above and value <= high and (not whole or value == int(value)):
        return
    kind = "a whole number" if whole else "a finite number"
    if math.isfinite(high):
        where = f" in {'(' if open_low else '['}{low:g}, {high:g}]"
    elif math.isfinite(low):
        where = f" {'>' if open_low else '>='} {low:g}"
    else:
        where = ""
    raise ValueError(f"{key} must be {kind}{where}, got {value:g}")


# The methods whose losses read a weight; sweeping it for another method changes nothing.
USED_BY = {
    "alpha": ("dear", "sear"),
    "beta": ("dear",),
    "recon_weight": ("sear",),
    "ted_weight": ("ted",),
}


def reads(method: str, key: str) -> bool:
    """Whether `method`'s update reads agent.`key` (every method reads the non-weights)."""
    return method in USED_BY.get(key, (method,))


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
    names = [f"{v:g}" for v in values]  # as Lane.label names them: the lanes' folders
    if len(set(names)) != len(names):
        same = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(
            f"sweep.{key}={text!r}: values named alike ({', '.join(f'{key}={n}' for n in same)}) "
            "would share a lane folder; give values that differ in their first 6 digits"
        )
    for value in values:
        try:
            check_value(key, value)
        except ValueError as e:
            raise ValueError(f"sweep.{key}={text!r}: {e}") from None
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
        if not reads(method, key):
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


def not_a_run(workdir: pathlib.Path, missing: str = "config.json") -> FileNotFoundError:
    """The error for a folder given as a run's workdir that lacks `missing`; for a folder of
    runs, it names them."""
    runs = sorted(p.parent.name for p in workdir.glob("*/config.json"))
    if runs:
        named = ", ".join(runs[:3]) + (", ..." if len(runs) > 3 else "")
        hint = f"{workdir} holds {len(runs)} runs ({named}): give them, e.g. {workdir / '*'}/"
    elif missing == "summary.json":
        hint = (
            "run.py writes it at a run's end, or when it is stopped (a run killed outright: "
            "rerun its command, which resumes it from its last checkpoint)"
        )
    elif not workdir.is_dir():
        return FileNotFoundError(f"{workdir} does not exist: give the workdir of a run")
    else:
        hint = "give the workdir of a run"
    return FileNotFoundError(f"{workdir / missing} not found: {hint}")


def groups(workdir: str | pathlib.Path) -> dict[str, list[pathlib.Path]]:
    """A run workdir's lane folders grouped by setting ("" without a sweep), in lane order,
    from the config.json the trainer wrote there."""
    workdir = pathlib.Path(workdir)
    path = workdir / "config.json"
    if not path.is_file():
        raise not_a_run(workdir)
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

    config: dict  # the first workdir's config.json
    label: str  # its setting, e.g. "beta=10" (`pools`); "" for a method's own
    seeds: list[tuple[pathlib.Path, pathlib.Path]]
    # The numbers in which it is not its method's own setting: swept, or a loss weight changed
    changed: tuple[str, ...] = ()

    @property
    def workdirs(self) -> list[pathlib.Path]:
        return list(dict.fromkeys(w for w, _ in self.seeds))


def pools(workdirs, defaults: dict, ignored: tuple[str, ...]) -> list[Pool]:
    """The workdirs' lanes pooled by experiment: two workdirs hold seeds of the same experiment
    when their config.json agree on every field but `ignored` (the seeds, and what a run may
    change without changing what it learns) and the loss weights their method does not read, a
    field a config lacks read from `defaults` (the trainer's config of today, flattened, so
    runs logged before a field existed keep its default); lanes pool by setting. A seed is
    (config.seed, lane seed): the same seed in two workdirs is refused, since it would be
    counted twice.

    A pool's label names its values of the per-lane numbers (`SWEEPABLE`) its method reads that
    set it apart: those its run swept, the loss weights it changed from `defaults`, and those in
    which it differs from another pool of its task and method ("beta=10_seed_0"'s "beta=10", or
    "beta=100" for the paper's DEAR beside a beta=10 run); `changed` the first two."""
    found: dict[tuple[str, str], Pool] = {}
    values: dict[tuple[str, str], dict] = {}  # each pool's per-lane numbers (its lane's values)
    origin: dict[tuple[str, str, tuple[int, int]], pathlib.Path] = {}
    settings: dict[tuple[str, str], dict] = {}  # each pool's fields that set it apart
    # a workdir named twice (overlapping globs, a relative and an absolute path) counts once
    unique: dict[pathlib.Path, pathlib.Path] = {}
    for workdir in map(pathlib.Path, workdirs):
        unique.setdefault(workdir.resolve(), workdir)
    for workdir in unique.values():
        by_setting = groups(workdir)
        config = json.loads((workdir / "config.json").read_text())
        fields = {**defaults, **flatten(config)}
        method = fields.get("agent.method")
        for key in USED_BY:  # a weight its method does not read changes nothing
            if not reads(method, key) and f"agent.{key}" in defaults:
                fields[f"agent.{key}"] = defaults[f"agent.{key}"]
        kept = {k: v for k, v in fields.items() if k not in ignored and k != "seed"}
        key = json.dumps(kept, sort_keys=True, default=str)
        run_lanes = lanes(ConfigDict(config))
        seed_of = {lane.name: lane.seed for lane in run_lanes}
        for lane in run_lanes:
            numbers = {k: _number(fields.get(f"agent.{k}")) for k in SWEEPABLE if reads(method, k)}
            numbers.update(lane.settings)
            values.setdefault((key, lane.label), numbers)
            swept = dict(lane.settings)
            changed = tuple(
                k
                for k, v in numbers.items()
                if k in swept
                or (k in USED_BY and f"agent.{k}" in defaults and v != defaults[f"agent.{k}"])
            )
            found.setdefault((key, lane.label), Pool(config, "", [], changed))
            settings.setdefault((key, lane.label), kept)
        for label, dirs in by_setting.items():
            pool = found[key, label]
            for lane_dir in dirs:
                seed = (config.get("seed", 0), seed_of[lane_dir.name])
                first = origin.setdefault((key, label, seed), workdir)
                if first != workdir:
                    raise ValueError(
                        f"{first} and {workdir} both trained seed {seed[1]} of config.seed="
                        f"{seed[0]} of the same experiment: the same seed twice. Report one of "
                        "them (leave the other out); give each new run of an experiment its own "
                        "--config.seed"
                    )
                pool.seeds.append((workdir, lane_dir))

    def experiment(pool):
        return pool.config.get("env", {}).get("task"), pool.config.get("agent", {}).get("method")

    for pool_key, pool in found.items():
        same = [values[k] for k, p in found.items() if experiment(p) == experiment(pool)]
        mine = values[pool_key]
        varying = {k for k in mine if len({json.dumps(v.get(k)) for v in same}) > 1}
        pool.label = "_".join(
            f"{k}={mine[k]:g}" if isinstance(mine[k], float) else f"{k}={mine[k]}"
            for k in mine
            if k in pool.changed or k in varying
        )
    # Pools of one task and method split by a field that is not a per-lane number (a dtype, envs
    # per seed, the replay's size, ...) would read alike: their labels name the first such fields.
    alike: dict[tuple, list[tuple[str, str]]] = {}
    for pool_key, pool in found.items():
        alike.setdefault((*experiment(pool), pool.label), []).append(pool_key)
    lane_fields = {f"agent.{k}" for k in SWEEPABLE}
    for group in (g for g in alike.values() if len(g) > 1):
        keys = sorted(set().union(*(settings[k] for k in group)) - lane_fields)
        apart = [
            k for k in keys if len({json.dumps(settings[g].get(k), default=str) for g in group}) > 1
        ]
        for pool_key in group:
            named = [f"{k}={settings[pool_key].get(k)}" for k in apart[:2]]
            more = [f"+{len(apart) - 2} more"] if len(apart) > 2 else []
            found[pool_key].label = " ".join([found[pool_key].label, *named, *more]).strip()
    return list(found.values())


def _number(value):
    """An int or float field's value as a float (1000 and 1000.0 are one setting)."""
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    return float(value) if is_number else value


def flatten(tree: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1}."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out
