"""Command-line config checks that need no jax: unknown `--config.key` overrides."""

from __future__ import annotations

import difflib

from ml_collections import ConfigDict


def check_override_keys(config: ConfigDict, argv: list[str]) -> None:
    """Reject `--config.a.b=...` arguments whose key the config does not have, before parsing.

    The message names the unknown part, the closest valid key and every valid key at that level.
    """
    for arg in argv:
        if not arg.startswith("--config."):
            continue
        dotted = arg[len("--config.") :].split("=", 1)[0]
        node, path = config, []
        for part in dotted.split("."):
            if not isinstance(node, ConfigDict) or part not in node:
                valid = sorted(node.keys()) if isinstance(node, ConfigDict) else []
                where = ".".join(path) or "the config"
                close = difflib.get_close_matches(part, valid, n=1)
                hint = f" Did you mean {'.'.join([*path, close[0]])!r}?" if close else ""
                raise KeyError(
                    f"unknown config key {dotted!r}: {where} has no field {part!r}.{hint} "
                    f"Valid fields of {where}: {', '.join(valid) or '(none: it is a value)'}"
                )
            node, path = node[part], [*path, part]
