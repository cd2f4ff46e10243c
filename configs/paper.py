"""Any experiment of the paper's grid from one file, named by its config string:

    python run.py --config configs/paper.py:TASK,METHOD[,DIFFICULTY[,MASK]]

This is the one way to name an experiment of the grid; the other files of configs/ are the
promised walker_dear.py and smoke.py, DrQ-v2's own walker settings and the two ablations.

TASK: walker, cup, finger (Distracting Control Suite) or light, kettle (Franka Kitchen);
METHOD: drqv2, dear, sear, ted; DIFFICULTY (DMC only): none, easy, medium (default), hard:
the paper's setting, background videos only, static, a new video each episode; with "-full"
(e.g. medium-full) the full Distracting Control Suite: background, colours and camera;
MASK: true (default), noisy (each agent pixel dropped with p = 0.8), approximate.
E.g. `paper.py:cup,sear,hard` or `paper.py:walker,dear,medium-full,noisy`. The default workdir
is runs/paper_<the parts joined by _>. The weight ablations are sweeps in one run:
walker_dear_beta_sweep.py and walker_dear_loss_ablation.py.
"""

from ml_collections import ConfigDict

from configs import base, kitchen

METHODS = ("drqv2", "dear", "sear", "ted")
LEVELS = ("easy", "medium", "hard")
DIFFICULTIES = ("none", *LEVELS, *(f"{d}-full" for d in LEVELS))
MASKS = ("true", "noisy", "approximate")


def get_config(spec: str = "walker,dear,medium") -> ConfigDict:
    parts = [p.strip() for p in spec.split(",")]
    if not 2 <= len(parts) <= 4:
        raise ValueError(f"config string {spec!r}: give TASK,METHOD[,DIFFICULTY[,MASK]]")
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
    return c
