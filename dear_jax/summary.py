"""A run's summary: each lane's final and best evaluation, the means over each setting's seeds,
and what the run ran on, as summary.md and summary.json in its workdir."""

from __future__ import annotations

import json
import math
import os

import jax
import numpy as np

import envs
from dear_jax import lanes, networks
from dear_jax.logger import format_table, read_csv, write_text_atomic
from dear_jax.provenance import provenance

# How many runs share this run's GPU (or CPU) side by side, its own included: `dear_jax.grid
# --per-gpu K` starts its jobs with this set to K. The summary records it, so that a run's pace
# says what it was measured beside (`report table` notes pooled runs that differ in it).
RUNS_PER_GPU_ENV = "DEAR_JAX_RUNS_PER_GPU"


def runs_per_gpu() -> int:
    """$DEAR_JAX_RUNS_PER_GPU (1 when unset); a clear error for a value that is no count."""
    text = os.environ.get(RUNS_PER_GPU_ENV, "1")
    count = int(text) if text.strip().isdigit() else 0
    if count < 1:
        raise ValueError(
            f"{RUNS_PER_GPU_ENV}={text!r}: give how many runs share this run's GPU side by side "
            "(its own included), an integer >= 1"
        )
    return count


def _best(values: np.ndarray) -> float:
    """The largest non-NaN value; NaN when there is none (a run stopped before evaluating)."""
    return float(np.nanmax(values)) if np.isfinite(values).any() else math.nan


# The train log's account of an iteration (dear_jax.loop.Loop.host_seconds), as the summary
# words it: column -> words for its ms.
STAGES = {
    "env_action_ms": "waited {:.1f} ms for the agent's actions (queued behind its updates)",
    "env_physics_ms": "stepped {:.1f}",
    "env_draw_ms": "drew {:.1f}",
    "env_post_ms": "uploaded {:.1f}",
}


def stage_means(train_log: dict[str, np.ndarray], rows=slice(None)) -> dict[str, float]:
    """ms per iteration of the train log's `iteration_ms` and the host's stages (every `*_ms`
    column), over its `rows` that have them, each row weighted by its `iterations` (a log
    without that column: equally; rows written before it, by older code: left out)."""
    weights = train_log.get("iterations", np.ones(len(train_log["frame"])))[rows]
    means = {}
    for k, v in train_log.items():
        if not k.endswith("_ms"):
            continue
        timed = np.isfinite(v[rows]) & np.isfinite(weights)
        if timed.any():
            means[k] = float(np.average(v[rows][timed], weights=weights[timed]))
    return means


def _stages_line(ms: dict[str, float]) -> str:
    """Where the training's iterations went, as the summary says it (empty without the log)."""
    if "iteration_ms" not in ms:
        return ""
    stages = ", ".join(words.format(ms[k]) for k, words in STAGES.items() if k in ms)
    return f"; {ms['iteration_ms']:.1f} ms an iteration: the env {stages}"


def _distraction_line(spec: envs.EnvSpec) -> str:
    """What the run's frames were distracted by, as the summary says it."""
    if spec.distraction == "none":
        return "no distraction"
    kinds = ", ".join(spec.distraction_types)
    return (
        f"distraction {spec.distraction} ({kinds}; {'dynamic' if spec.dynamic else 'static'}; "
        f"backgrounds: {spec.backgrounds})"
    )


def write_summary(
    workdir,
    config,
    spec,
    counters,
    *,
    devices: int = 1,
    stopped: str | None = None,
    evaluated_on: str,
    eval_processes: int = 1,
    runs_per_gpu: int = 1,
) -> dict:
    """Summary per seed from the eval logs, saved as summary.md / summary.json and printed
    unless the run was `stopped` (by that signal's name) before its end. `evaluated_on`: the
    resolved eval_device; `eval_processes`: how many evaluated side by side; `runs_per_gpu`:
    how many runs trained side by side on its GPU (`runs_per_gpu()`)."""
    wall = counters["wall_s"]
    runs = lanes.lanes(config)
    fps = counters["frame"] * len(runs) / max(wall, 1e-9)
    rows, per_seed = [], []
    for lane in runs:
        path = workdir / lane.name / "eval.csv"
        evals = read_csv(path) if path.exists() else {}
        returns = evals.get("episode_return", np.array([np.nan]))
        abs_cos = evals.get("abs_cos_agent_env", np.array([np.nan]))
        cos = evals.get("cos_agent_env", np.array([np.nan]))
        best = _best(returns)
        per_seed.append(
            dict(
                seed=lane.seed,
                lane=lane.name,
                settings=dict(lane.settings),
                final_return=float(returns[-1]),
                best_return=best,
                cos_agent_env=float(cos[-1]),
                abs_cos_agent_env=float(abs_cos[-1]),
            )
        )
        rows.append([lane.name, f"{returns[-1]:.1f}", f"{best:.1f}", f"{abs_cos[-1]:.2e}"])
        if spec.has_success:  # success rate of the eval episodes (kitchen)
            success = evals.get("success", np.array([np.nan]))
            per_seed[-1].update(final_success=float(success[-1]), best_success=_best(success))
            rows[-1].append(f"{success[-1]:.2f}")
    train_path = workdir / runs[0].name / "train.csv"  # the stages are the same for every lane
    ms = stage_means(read_csv(train_path)) if train_path.exists() else {}
    for label in dict.fromkeys(lane.label for lane in runs):  # mean over each setting's seeds
        group = [p for p, lane in zip(per_seed, runs) if lane.label == label]
        finals = np.array([p["final_return"] for p in group])
        rows.append([f"mean {label}".strip(), f"{finals.mean():.1f} ± {finals.std():.1f}", "", ""])
        if spec.has_success:
            rates = np.array([p["final_success"] for p in group])
            rows[-1].append(f"{rates.mean():.2f} ± {rates.std():.2f}")
    summary = {
        "task": config.env.task,
        "method": config.agent.method,
        "action_dim": spec.action_dim,
        "seeds": config.seeds,
        "lanes": len(runs),
        "sweep": {k: list(v) for k, v in lanes.sweep_values(config).items()},
        "devices": devices,
        "devices_per_seed": config.devices_per_seed,
        "processes": jax.process_count(),
        "envs_per_seed": config.envs_per_seed,
        "frames_per_seed": counters["frame"],
        "updates_per_seed": counters["updates"],
        "wall_s": wall,
        "aggregate_fps": fps,
        "host_ms_per_iteration": ms,
        "backend": spec.backend,
        "device": jax.devices()[0].device_kind,
        "conv_stack": networks.stack_for(config.agent.conv_stack),
        "kernels": config.agent.kernels,
        "render": {**config.env.render.to_dict(), "gpus": spec.render_gpus},
        "render_quality": config.env.render.quality,
        "eval_device": evaluated_on,
        "eval_processes": eval_processes,
        "runs_per_gpu": runs_per_gpu,
        "distraction": config.env.distraction,
        "distraction_types": list(spec.distraction_types),
        "backgrounds": spec.backgrounds,
        "noise_hold": config.agent.noise_hold,
        "replay_sampling": config.replay.sampling,
        "stopped": stopped,
        "per_seed": per_seed,
        "provenance": provenance(),
    }
    unit = "lane" if runs[0].settings else "seed"
    columns = [unit, "final eval return", "best eval return", "abs cos(z_A, z_E)"]
    columns += ["final eval success"] if spec.has_success else []
    table = format_table(columns, rows)
    until = f"stopped by {stopped} at " if stopped else ""
    kernels = (
        f" ({config.agent.kernels})"
        if config.agent.kernels and summary["conv_stack"] == "pallas"
        else ""
    )
    evaluators = f", {eval_processes} processes" if eval_processes > 1 else ""
    evaluators += f"; {runs_per_gpu} runs side by side on this device" if runs_per_gpu > 1 else ""
    held = config.agent.noise_hold
    notes = f"; exploration draws held {held:g} agent steps" if held != 1 else ""
    notes += "; replay sampled by episode" if config.replay.sampling == "episode" else ""
    on = summary["device"] if devices == 1 else f"{devices} x {summary['device']}"
    if config.devices_per_seed > 1:
        on += f", {config.devices_per_seed} per {unit}"
    prov = summary["provenance"]
    text = (
        f"# {config.agent.method} on {config.env.task}\n\n"
        f"{until}{counters['frame']:,} frames per {unit} x {len(runs)} {unit}s, "
        f"{wall:.0f} s of training ({fps:.0f} frames/s in all{_stages_line(ms)}) on {on} "
        f"({spec.backend} physics, {summary['conv_stack']} conv stacks{kernels}, evaluations on "
        f"{summary['eval_device']}{evaluators}); {_distraction_line(spec)}{notes}; render "
        f"settings {summary['render']}; commit {prov['commit']}, jax {prov['jax']}, flax "
        f"{prov['flax']}, mujoco {prov['mujoco']}\n\n{table}\n"
    )
    write_text_atomic(workdir / "summary.md", text)
    write_text_atomic(workdir / "summary.json", json.dumps(summary, indent=1))
    if not stopped:
        print(text)
    return summary
