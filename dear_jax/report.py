"""Command-line reports about the agent: `python -m dear_jax.report params [--action-dim 6]`.

`params` prints the parameter count of every module per method (walker: |A| = 6), computed from
shapes only (jax.eval_shape), so it is instant and allocates nothing.
"""

from __future__ import annotations

import argparse
import functools
import math

import jax

from dear_jax.update import METHODS, AgentConfig, init_params

MODULES = ("encoder", "actor", "critic", "mask_decoder", "recon_decoder", "ted")


def param_counts(cfg: AgentConfig) -> dict[str, int]:
    shapes = jax.eval_shape(functools.partial(init_params, cfg), jax.random.key(0))
    return {
        name: sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(tree))
        for name, tree in shapes.items()
    }


def params_table(action_dim: int = 6) -> list[tuple[str, dict[str, int]]]:
    rows = [(m, param_counts(AgentConfig(action_dim=action_dim, method=m))) for m in METHODS]
    rows.append(
        (
            "drqv2 (plain encoder)",
            param_counts(AgentConfig(action_dim=action_dim, method="drqv2", encoder="plain")),
        )
    )
    return rows


def format_params_table(rows) -> str:
    header = ["method", *MODULES, "total"]
    lines = [header]
    for method, counts in rows:
        cells = [f"{counts[m]:,}" if m in counts else "-" for m in MODULES]
        lines.append([method, *cells, f"{sum(counts.values()):,}"])
    widths = [max(len(r[i]) for r in lines) for i in range(len(header))]
    fmt = lambda r: "| " + " | ".join(c.rjust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([fmt(lines[0]), sep, *map(fmt, lines[1:])])


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m dear_jax.report", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("params", help="parameter counts per method and module")
    p.add_argument("--action-dim", type=int, default=6, help="|A| (walker: 6)")
    args = parser.parse_args(argv)
    if args.command == "params":
        print(f"Parameters per module, |A| = {args.action_dim}")
        print(format_params_table(params_table(args.action_dim)))


if __name__ == "__main__":
    main()
