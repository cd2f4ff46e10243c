"""Hardware counters of one learner update's Pallas conv-stack kernels, read by Nsight Compute.

python -m benchmarks.kernel_counters [--method dear] [--seeds 1] [--batch 512]
    [--kernels NAME=INT,...] [--match REGEX] [--sections SECTION ...] --out FILE.json

Runs itself once to fill JAX's persistent compilation cache ($JAX_COMPILATION_CACHE_DIR, else a
new temporary folder), then under `ncu` (`--clock-control none`: the GPU's clocks as found;
`--target-processes application-only`: not the processes it starts), which profiles every
kernel whose name matches --match (default: the conv stacks' `_conv_kernel` and `_wgrad_kernel`)
in two updates, a warm-up one and a measured one, replaying each kernel once per counter pass.
The measured update's kernels, in launch order, are written with their sections' metrics (by
default ncu's speed of light, memory and compute workloads, warp stall reasons, occupancy and
launch statistics) to the JSON, and ncu's whole CSV beside it (FILE.csv). The table printed
shows per kernel: duration, the throughput of DRAM, L2, L1 and the SMs as percents of their
peaks, achieved occupancy and registers per thread: whether a kernel is bound by memory, by a
cache or by latency. (ncu flushes the caches before each replay, so durations are a little
above those in an update.)

The update is the bf16 one, seeds on the hybrid axis, with the Pallas conv stacks (the settings of
`benchmarks.update`'s figures); XLA's command buffers are off in the profiled process so that
each kernel launches on its own (the kernels themselves are the same).
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

from dear_jax.update import METHODS

SECTIONS = (
    "SpeedOfLight",
    "MemoryWorkloadAnalysis",
    "ComputeWorkloadAnalysis",
    "WarpStateStats",
    "Occupancy",
    "LaunchStats",
)
MATCH = "_conv_kernel|_wgrad_kernel"
# The columns of the printed table: (header, section, metric name as ncu prints it)
COLUMNS = (
    ("us", "GPU Speed Of Light Throughput", "Duration"),
    ("DRAM %", "GPU Speed Of Light Throughput", "DRAM Throughput"),
    ("L2 %", "GPU Speed Of Light Throughput", "L2 Cache Throughput"),
    ("L1 %", "GPU Speed Of Light Throughput", "L1/TEX Cache Throughput"),
    ("SM %", "GPU Speed Of Light Throughput", "Compute (SM) Throughput"),
    ("occupancy %", "Occupancy", "Achieved Occupancy"),
    ("registers", "Launch Statistics", "Registers Per Thread"),
)


def parse_details_csv(text: str) -> list[dict]:
    """ncu's `--csv --page details` output -> one dict per profiled kernel, in launch order:
    {"id", "name", "grid", "block", "metrics": {"SECTION / METRIC": [value, unit]}}. Lines
    before the header (ncu's own messages, the program's output) are skipped; a value is a
    float where it reads as one (thousands separators dropped), else the text."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith('"ID",')), None)
    if start is None:
        raise ValueError("no ncu CSV header (a line starting with '\"ID\",') in the output")
    rows = csv.DictReader(line for line in lines[start:] if not line.startswith("=="))
    kernels: dict[str, dict] = {}
    for row in rows:
        if not row.get("Metric Name") or row.get("ID") in (None, "ID"):
            continue
        kernel = kernels.setdefault(
            row["ID"],
            {
                "id": int(row["ID"]),
                "name": row["Kernel Name"],
                "grid": row.get("Grid Size", ""),
                "block": row.get("Block Size", ""),
                "metrics": {},
            },
        )
        key = f"{row['Section Name']} / {row['Metric Name']}"
        kernel["metrics"][key] = [_number(row["Metric Value"]), row.get("Metric Unit", "")]
    return sorted(kernels.values(), key=lambda k: k["id"])


def _number(text: str):
    try:
        return float(text.replace(",", ""))
    except ValueError:
        return text


def measured_update(kernels: list[dict]) -> list[dict]:
    """The last update's kernels: the shortest tail that repeats the launches just before it and
    launches every kernel profiled (kernels of the set-up, if any, come first). A ValueError
    when no such tail exists (the updates launched different kernels)."""
    names = [k["name"] for k in kernels]
    for p in range(1, len(names) // 2 + 1):
        if names[-p:] == names[-2 * p : -p] and set(names[-p:]) == set(names):
            return kernels[-p:]
    raise ValueError(f"no repeated update among the {len(names)} kernels profiled: {names[:8]}...")


def table(kernels: list[dict]) -> str:
    """A markdown table of COLUMNS, one row per kernel ("-" where ncu gave no such metric)."""
    head = ["#", "kernel", "grid", *[c[0] for c in COLUMNS]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, k in enumerate(kernels):
        cells = []
        for _, section, metric in COLUMNS:
            value, unit = k["metrics"].get(f"{section} / {metric}", ("-", ""))
            if isinstance(value, float) and unit in ("ns", "nsecond"):
                value /= 1e3  # the Duration column is in µs
            elif isinstance(value, float) and unit in ("ms", "msecond"):
                value *= 1e3
            cells.append(f"{value:.1f}" if isinstance(value, float) else str(value))
        lines.append("| " + " | ".join([str(i), k["name"][:40], k["grid"], *cells]) + " |")
    return "\n".join(lines)


def find_ncu(name: str) -> str | None:
    """`name` on PATH, else the newest ncu of CUDA's or Nsight Compute's usual install folders."""
    found = shutil.which(name)
    if found or os.sep in name:
        return found
    places = sorted(glob.glob("/usr/local/cuda*/bin/ncu")) + sorted(
        glob.glob("/opt/nvidia/nsight-compute/*/ncu")
    )
    return places[-1] if places else None


def run_ncu(command: list[str], env: dict) -> tuple[str, int]:
    """Runs ncu, passing its own messages ("==PROF== Profiling ...", one per kernel; warnings;
    errors) and the target's output to stderr as they come: -> (the CSV, the exit status)."""
    with subprocess.Popen(
        command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    ) as process:
        csv_lines = []
        for line in process.stdout:
            if line.startswith('"'):
                csv_lines.append(line)
            else:
                print(line, end="", file=sys.stderr, flush=True)
    return "".join(csv_lines), process.returncode


def run_target(args) -> None:
    """Inside ncu: a warm-up update and a measured one."""
    import jax

    from benchmarks.update import update_setup

    step, states, batches, hp = update_setup(
        args.method,
        args.seeds,
        args.batch,
        "bfloat16",
        "hybrid",
        conv_stack="pallas",
        kernels=args.kernels,
    )
    for i in range(2):
        keys = jax.random.split(jax.random.key(i), args.seeds)
        states, metrics = step(states, batches, keys, hp)
        jax.block_until_ready(metrics)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--method", default="dear", choices=METHODS)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--kernels", default="", help="the Pallas stacks' constants, NAME=INT,...")
    parser.add_argument("--match", default=MATCH, help="regex of the kernel names to profile")
    parser.add_argument("--sections", nargs="+", default=list(SECTIONS))
    parser.add_argument("--ncu", default="ncu", help="the Nsight Compute command")
    parser.add_argument("--target", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    if args.target:
        return run_target(args)
    ncu = find_ncu(args.ncu)
    if ncu is None:
        parser.error(
            f"Nsight Compute ({args.ncu!r}) is not on PATH: run this on a GPU machine with ncu"
        )
    target = [sys.executable, "-m", "benchmarks.kernel_counters", "--target"]
    target += ["--method", args.method, "--seeds", str(args.seeds), "--batch", str(args.batch)]
    target += ["--kernels", args.kernels]
    command = [ncu, "--clock-control", "none", "--target-processes", "application-only"]
    command += ["--kernel-name", f"regex:{args.match}"]
    command += [arg for s in args.sections for arg in ("--section", s)]
    command += ["--csv", "--page", "details", "--print-units", "base", *target]
    with tempfile.TemporaryDirectory(prefix="kernel_counters_cache_") as fresh:
        env = dict(
            os.environ,
            XLA_FLAGS=(
                os.environ.get("XLA_FLAGS", "") + " --xla_gpu_enable_command_buffer="
            ).strip(),
            # ncu saves and restores the device memory around each replayed pass: with JAX's
            # preallocated pool (most of the GPU) every pass would copy it all.
            XLA_PYTHON_CLIENT_PREALLOCATE="false",
            # Every program into the persistent cache, compiled by a first run outside ncu
            # (under which compiling, autotuning's kernels included, takes minutes)
            JAX_COMPILATION_CACHE_DIR=os.environ.get("JAX_COMPILATION_CACHE_DIR") or fresh,
            JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        )
        print("compiling outside ncu", file=sys.stderr, flush=True)
        subprocess.check_call(target, env=env)
        csv_text, returncode = run_ncu(command, env)
    if args.out:
        csv_path = pathlib.Path(args.out).with_suffix(".csv")
        csv_path.parent.mkdir(parents=True, exist_ok=True)
        csv_path.write_text(csv_text)
    if returncode:
        sys.exit(f"ncu exited with {returncode}")
    kernels = measured_update(parse_details_csv(csv_text))
    print(f"{args.method}, {args.seeds} seed(s), batch {args.batch}: {len(kernels)} kernels")
    print(table(kernels))
    from benchmarks.common import save_json

    # ncu's arguments as anyone reruns them (the interpreter by name, not by its path here)
    recorded = command[1 : -len(target)] + ["python", *target[1:]]
    save_json({"ncu_command": recorded, "kernels": kernels}, args.out)


if __name__ == "__main__":
    main()
