"""Command-line config checks that need no jax: config file names, unknown `--config.key`,
values a field's type does not take."""

from __future__ import annotations

import difflib
import pathlib
import runpy
import sys

from absl import flags
from ml_collections import ConfigDict

# The parsers ml_collections gives `--config.KEY=VALUE` of fields of these types (absl's), and
# what each takes in words.
_SCALAR_PARSERS = {
    bool: (flags.BooleanParser(), "true or false"),
    int: (flags.IntegerParser(), "an integer"),
    float: (flags.FloatParser(), "a number"),
}


def check_override_keys(config: ConfigDict, argv: list[str]) -> None:
    """Reject `--config.a.b=...` arguments whose key the config does not have (KeyError), or
    whose value a bool, int or float field does not take (ValueError), before parsing.

    The message names the unknown part, the closest valid key and every valid key at that level;
    or the field, its type and the value given.
    """
    for arg in argv:
        if not arg.startswith("--config."):
            continue
        dotted, eq, value = arg[len("--config.") :].partition("=")
        node, path, parent = config, [], None
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
            parent, node, path = node, node[part], [*path, part]
        # The field's declared type, not its value's: a FieldReference of type object (devices:
        # an int or "all") takes what ml_collections makes of the text.
        parser, takes = _SCALAR_PARSERS.get(parent.get_type(path[-1]), (None, ""))
        if eq and parser is not None:
            try:
                parser.parse(value)
            except ValueError:
                raise ValueError(
                    f"--config.{dotted}={value}: {dotted} takes {takes} (the config's: "
                    f"{node!r}), not {value!r}"
                ) from None


# Files of configs/ that other configs build on, not runs' configs (not listed as choices).
SETTINGS_ONLY = ("base.py", "kitchen.py")


def resolve_config_path(name: str, configs_dir: str | pathlib.Path) -> pathlib.Path:
    """A config file from a path, or a bare name looked up in `configs_dir` (".py" optional).

    Raises FileNotFoundError listing the configs when neither exists.
    """
    configs_dir = pathlib.Path(configs_dir)
    path = pathlib.Path(name)
    if path.is_file():
        return path
    if path.parent == pathlib.Path("."):
        for candidate in (configs_dir / path.name, configs_dir / f"{path.name}.py"):
            if candidate.is_file() and candidate.name != "__init__.py":
                return candidate
    available = sorted(
        p.name for p in configs_dir.glob("*.py") if p.name not in ("__init__.py", *SETTINGS_ONLY)
    )
    close = difflib.get_close_matches(path.name, available, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    raise FileNotFoundError(
        f"config file {name!r} not found (nor in {configs_dir}).{hint} "
        f"Configs in {configs_dir}: {', '.join(available)}"
    )


CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs"


def load_config(value: str) -> ConfigDict:
    """The config `run.py --config=VALUE` trains: a file path or a bare name in configs/, and
    after a colon the string its get_config() takes (e.g. "paper.py:walker,dear")."""
    if str(CONFIGS.parent) not in sys.path:  # the config files import `configs.base`
        sys.path.insert(0, str(CONFIGS.parent))
    name, *spec = value.split(":", 1)
    return runpy.run_path(str(resolve_config_path(name, CONFIGS)))["get_config"](*spec)
