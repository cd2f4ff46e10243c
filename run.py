"""Train DEAR or a baseline: `python run.py --config configs/walker_dear.py [--workdir DIR]`.

Any config field can be overridden: `--config.seeds=5 --config.agent.beta=10`. Rerunning the same
command on the same workdir resumes from its latest checkpoint.
"""

import logging
import pathlib
import runpy
import sys

from absl import app, flags
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file("config", None, "experiment config file (configs/*.py)")
_WORKDIR = flags.DEFINE_string(
    "workdir", None, "output folder (default: runs/<config file name>); reused to resume"
)
flags.mark_flags_as_required(["config"])


def _check_argv(argv):
    """Friendly errors for a missing config file or an unknown --config.key, before absl parses."""
    from dear_jax.config import check_override_keys

    path = next((a.split("=", 1)[1] for a in argv if a.startswith("--config=")), None)
    if path is None and "--config" in argv[:-1]:
        path = argv[argv.index("--config") + 1]
    if path is None:
        return
    if not pathlib.Path(path).is_file():
        available = ", ".join(sorted(p.name for p in pathlib.Path("configs").glob("*.py")))
        sys.exit(f"error: config file {path!r} not found; configs/ has: {available}")
    check_override_keys(runpy.run_path(path)["get_config"](), argv)


def main(argv):
    del argv
    from dear_jax.train import train

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    config_path = flags.FLAGS["config"].config_filename
    workdir = _WORKDIR.value or str(pathlib.Path("runs") / pathlib.Path(config_path).stem)
    train(_CONFIG.value, workdir)


if __name__ == "__main__":
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    try:
        _check_argv(sys.argv[1:])
    except KeyError as e:
        sys.exit(f"error: {e.args[0]}")
    app.run(main)
