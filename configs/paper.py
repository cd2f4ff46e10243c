"""Any experiment of the paper's grid from one file, named by its config string:

    python run.py --config configs/paper.py:TASK,METHOD[,DIFFICULTY[,MASK]][,WEIGHT=VALUE...]

This is the one way to name an experiment of the grid; the other files of configs/ are the
promised walker_dear.py and smoke.py, DrQ-v2's own walker settings and the two ablations.

TASK: walker, cup, finger (Distracting Control Suite) or light, kettle (Franka Kitchen);
METHOD: drqv2, dear, sear, ted; DIFFICULTY (DMC only): none, easy, medium (default), hard:
the paper's setting, background videos only, static, a new video each episode; with "-full"
(e.g. medium-full) the full Distracting Control Suite: background, colours and camera;
MASK: true (default), noisy (each agent pixel dropped with p = 0.8), approximate.
WEIGHT=VALUE (after the others, any number): a number of the update the method reads, as a sweep
may vary it (dear_jax/lanes.py, e.g. beta=10, alpha=0): one setting of the weight ablations;
or sampling=episode: the replay sampled as DrQ-v2's code samples it (replay.sampling).
E.g. `paper.py:cup,sear,hard`, `paper.py:walker,dear,medium-full,noisy` or
`paper.py:walker,dear,alpha=0,beta=0`. The default workdir is runs/paper_<the parts joined by _>.
The weight ablations as sweeps in one run: walker_dear_beta_sweep.py, walker_dear_loss_ablation.py.
"""

from ml_collections import ConfigDict

from configs import base, kitchen
from dear_jax import lanes, replay

METHODS = ("drqv2", "dear", "sear", "ted")
LEVELS = ("easy", "medium", "hard")
DIFFICULTIES = ("none", *LEVELS, *(f"{d}-full" for d in LEVELS))
MASKS = ("true", "noisy", "approximate")


def get_config(spec: str = "walker,dear,medium") -> ConfigDict:
    parts = [p.strip() for p in spec.split(",")]
    weights = [p for p in parts if "=" in p]
    parts = parts[: len(parts) - len(weights)]
    if not 2 <= len(parts) <= 4 or "=" in ",".join(parts):
        raise ValueError(
            f"config string {spec!r}: give TASK,METHOD[,DIFFICULTY[,MASK]][,WEIGHT=VALUE...]"
        )
    task, method, difficulty, mask = parts + ["medium", "true"][len(parts) - 2 :]
    tasks = (*base.TASK_SHORT_NAMES, *kitchen.KITCHEN_TASKS)
    for name, value, valid in (
        ("task", task, tasks),
        ("method", method, METHODS),
        ("difficulty", difficulty, DIFFICULTIES),
        ("mask", mask, MASKS),
    ):
        if value not in valid:
            raise ValueError(f"unknown {name} {value!r} in {spec!r}; valid: {', '.join(valid)}")
    if task in kitchen.KITCHEN_TASKS:
        if len(parts) > 2 and difficulty != "none":
            raise ValueError(f"{spec!r}: the kitchen has no distraction; give {task},{method}")
        c = kitchen.make(task, method)
    else:
        level, full = difficulty.removesuffix("-full"), difficulty.endswith("-full")
        c = base.make(task, method, level)
        if level != "none":
            c.env.distraction_types = "all" if full else "background"
    c.env.mask = mask
    given = set()
    for part in weights:
        name, value = (x.strip() for x in part.split("=", 1))
        if name not in (*lanes.SWEEPABLE, "sampling"):
            valid = ", ".join((*lanes.SWEEPABLE, "sampling"))
            raise ValueError(f"unknown setting {name!r} in {spec!r}; valid: {valid}")
        if name in given:
            raise ValueError(f"{name} given twice in {spec!r}")
        given.add(name)
        if name == "sampling":
            if value not in replay.SAMPLINGS:
                valid = ", ".join(replay.SAMPLINGS)
                raise ValueError(f"{part!r} in {spec!r}: the replay's sampling is one of {valid}")
            c.replay.sampling = value
            continue
        if not lanes.reads(method, name):
            readers = lanes.USED_BY[name]
            raise ValueError(
                f"{part!r} in {spec!r}: {method} does not read {name} (read by "
                f"{', '.join(readers)})"
            )
        kind = type(c.agent[name])
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"{part!r} in {spec!r}: give a number, e.g. {name}=10") from None
        if kind is int and not number.is_integer():
            raise ValueError(f"{part!r} in {spec!r}: {name} is a whole number")
        c.agent[name] = kind(number)
    return c
