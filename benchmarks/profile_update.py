"""Where the time of one learner update goes, on the GPU, per network part.

python -m benchmarks.profile_update [--method dear] [--batch 512] [--seeds 1] [--iters 10]

Traces a few jitted updates with `jax.profiler`, reads the device's kernel events back with
`jax.profiler.ProfileData`, and charges each kernel to the part of the update that emitted it
(encoder, mask decoder, critic, ...), using the op names Flax writes into the compiled HLO's
metadata. Prints a table of ms per update per part and the slowest kernels; writes JSON.
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import re
import tempfile

import jax

from benchmarks.common import save_json
from benchmarks.update import update_setup
from dear_jax import networks, update

PARTS = (  # first match wins; matched against the op's Flax/JAX name path
    ("mask decoder", r"PoolDecoder|mask_decoder"),
    ("encoder", r"PoolEncoder|PlainEncoder|ConvTrunk"),
    ("augmentation", r"random_shift|dynamic_slice|pad"),
    ("actor", r"Actor"),
    ("critic", r"Critic"),
    ("optimizer", r"adam|apply_updates|incremental_update|optax"),
    ("random numbers", r"random|_normal|_uniform|threefry"),
)


def part_of(op_name: str) -> str:
    for part, pattern in PARTS:
        if re.search(pattern, op_name):
            return part
    return "other"


def hlo_op_names(compiled_text: str) -> dict[str, str]:
    """HLO instruction name -> the framework op name in its metadata (for fusions: the root's)."""
    names = {}
    for m in re.finditer(r"%([\w.\-]+) = .*?metadata=\{[^}]*op_name=\"([^\"]*)\"", compiled_text):
        names.setdefault(m.group(1), m.group(2))
    return names


def op_of(hlo_op: str, kernel: str) -> str:
    """The HLO instruction a kernel ran for. Inside a command buffer the event names the buffer,
    and the kernel is named after the fusion ("loop_select_fusion_2" for
    "loop_select_fusion.2")."""
    if hlo_op.startswith("command_buffer"):
        return re.sub(r"_(\d+)$", r".\1", kernel)
    return hlo_op


def device_events(trace_dir: str):
    """(kernel name, hlo op, duration ns) of every kernel the GPU ran during the trace."""
    from jax.profiler import ProfileData

    files = sorted(pathlib.Path(trace_dir).rglob("*.xplane.pb"))
    data = ProfileData.from_file(str(files[-1]))
    for plane in data.planes:
        if not plane.name.startswith("/device:GPU"):
            continue
        for line in plane.lines:
            if not line.name.startswith("Stream"):
                continue
            for ev in line.events:
                stats = dict(ev.stats)
                yield ev.name, str(stats.get("hlo_op", "")), ev.duration_ns


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--method", default="dear", choices=update.METHODS)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--seed-axis", default="loop", choices=update.SEED_AXES)
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    parser.add_argument("--iters", type=int, default=10)
    parser.add_argument("--conv-stack", default="xla", choices=networks.STACKS)
    parser.add_argument("--kernels", default="", help="the Pallas stacks' constants, NAME=INT,...")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--out", default=None)
    parser.add_argument("--hlo-out", default=None, help="write the compiled HLO text here")
    args = parser.parse_args()
    if jax.default_backend() != "gpu":
        parser.error("it reads the GPU's kernel events from a profile: run it on a GPU machine")

    step, states, batches, hp = update_setup(
        args.method,
        args.seeds,
        args.batch,
        args.dtype,
        args.seed_axis,
        conv_stack=args.conv_stack,
        kernels=args.kernels,
    )
    keys = jax.random.split(jax.random.key(0), args.seeds)
    compiled_text = step.lower(states, batches, keys, hp).compile().as_text()
    if args.hlo_out:  # the optimised HLO, to read the fusions the kernels are named after
        pathlib.Path(args.hlo_out).write_text(compiled_text)
    names = hlo_op_names(compiled_text)
    states, metrics = step(states, batches, keys, hp)
    jax.block_until_ready(metrics)

    trace_dir = tempfile.mkdtemp(prefix="dear_jax_trace_")
    jax.profiler.start_trace(trace_dir)
    for i in range(args.iters):
        states, metrics = step(states, batches, jax.random.split(jax.random.key(i), args.seeds), hp)
    jax.block_until_ready(metrics)
    jax.profiler.stop_trace()

    per_part = collections.Counter()
    per_kernel = collections.Counter()
    # By kind of op (the HLO name without its number): how many launches, how much time.
    kind_ns, kind_count = collections.Counter(), collections.Counter()
    kernel_part, kernel_op = {}, {}
    for kernel, hlo_op, ns in device_events(trace_dir):
        op = op_of(hlo_op, kernel)
        # dear_jax.wideconv's Triton kernels (named after their Python functions)
        part = "conv stacks" if kernel.startswith(("_conv_kernel", "_wgrad_kernel")) else None
        part = part or part_of(names.get(op, op))
        per_part[part] += ns
        key = f"{hlo_op or '?'} | {kernel[:60]}"
        per_kernel[key] += ns
        kernel_part[key] = part
        kernel_op[key] = names.get(op, "")
        kind = re.sub(r"\.\d+$", "", hlo_op or "?")
        kind_ns[kind] += ns
        kind_count[kind] += 1
    scale = 1e-6 / args.iters  # ns summed over iters -> ms per call
    total = sum(per_part.values()) * scale
    device = jax.devices()[0].device_kind
    print(
        f"{args.method} update, batch {args.batch}, {args.seeds} seed(s) ({args.seed_axis}), "
        f"{args.dtype}, {device}: {total:.2f} ms of GPU kernels per call"
    )
    print("| part | ms per call | share |\n|---|---:|---:|")
    for part, ns in per_part.most_common():
        print(f"| {part} | {ns * scale:.2f} | {ns * scale / total:.0%} |")
    print("\n| op kind | kernels per call | ms per call |\n|---|---:|---:|")
    for kind, ns in kind_ns.most_common(args.top):
        print(f"| {kind} | {kind_count[kind] / args.iters:.0f} | {ns * scale:.3f} |")
    print("\n| hlo op / kernel | part | ms per call |\n|---|---|---:|")
    for key, ns in per_kernel.most_common(args.top):
        print(f"| {key} | {kernel_part[key]} | {ns * scale:.3f} |")
    save_json(
        dict(
            device=device,
            jax=jax.__version__,
            args=vars(args),
            ms_per_call=total,
            parts={p: ns * scale for p, ns in per_part.most_common()},
            kernels_per_call=sum(kind_count.values()) / args.iters,
            kinds={
                k: dict(ms=ns * scale, kernels=kind_count[k] / args.iters)
                for k, ns in kind_ns.most_common()
            },
            kernels={k: ns * scale for k, ns in per_kernel.most_common(100)},
            # the framework op (Flax module path / JAX primitive) behind each of those kernels
            kernel_ops={k: kernel_op[k] for k, _ in per_kernel.most_common(100)},
        ),
        args.out,
        f"benchmarks/results/profile_{args.method}_gpu.json",
    )


if __name__ == "__main__":
    main()
