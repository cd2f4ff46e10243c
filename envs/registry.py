"""Task registry: name -> builder of an `Env`; `make` raises on unknown names, listing valid ones."""

from __future__ import annotations

from collections.abc import Callable

from envs import dmc, kitchen

_REGISTRY: dict[str, Callable[..., object]] = {}


def register(name: str, builder: Callable[..., object]) -> None:
    """Register `builder(**kwargs) -> Env` under `name` (e.g. "walker-walk")."""
    if name in _REGISTRY:
        raise ValueError(f"task {name!r} is already registered")
    _REGISTRY[name] = builder


def names() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def frames_per_episode(name: str) -> int:
    """The task's own episode length in frames (what `Env`'s episode_frames=None gives)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(names())}")
    task = {**dmc.TASKS, **kitchen.TASKS}.get(name)
    if task is None:  # registered by a builder alone: only its Env knows
        raise ValueError(
            f"task {name!r} was registered without a DMC or kitchen task, so its episode length "
            "is unknown before its env is built; give env.episode_frames"
        )
    return task.frames_per_episode(task.physics_model())


def make(name: str, **kwargs):
    """Build the env registered as `name`; see envs.base.Env for the keyword arguments."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(names())}")
    return _REGISTRY[name](**kwargs)


def _dmc_builder(task: dmc.DmcTask):
    def build(**kwargs):
        from envs.base import Env

        return Env(task, **kwargs)

    return build


def _kitchen_builder(task: kitchen.KitchenTask):
    def build(**kwargs):
        from envs.base import Env

        kwargs.setdefault("action_repeat", 1)  # docs/method.md: the kitchen acts every 0.08 s
        return Env(task, **kwargs)

    return build


for _task in dmc.TASKS.values():
    register(_task.name, _dmc_builder(_task))
for _task in kitchen.TASKS.values():
    register(_task.name, _kitchen_builder(_task))
