"""Train DEAR or a baseline: `python run.py --config walker_dear.py [--workdir DIR]`.

`--config` takes a file path or a bare name of a file in configs/. Any config field can be
overridden: `--config.seeds=5 --config.agent.beta=10`. Rerunning the same command on the same
workdir resumes from its latest checkpoint. SIGTERM or Ctrl-C checkpoints, then exits (with
128 + the signal's number); `--verbose` shows libraries' INFO logs, which otherwise go only to
<workdir>/log.txt.
"""

import logging
import pathlib
import runpy
import sys

from absl import app, flags
from ml_collections import config_flags

ROOT = pathlib.Path(__file__).resolve().parent

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "experiment config: a file path, or a bare name of a file in configs/"
)
_WORKDIR = flags.DEFINE_string(
    "workdir", None, "output folder (default: runs/<config file name>); reused to resume"
)
_VERBOSE = flags.DEFINE_bool("verbose", False, "show libraries' INFO logs on the console too")
flags.mark_flags_as_required(["config"])


def _resolve_argv(argv: list[str]) -> list[str]:
    """argv with --config's bare name made a path; friendly errors for a missing config file or
    an unknown --config.key, before absl parses."""
    from dear_jax.config import check_override_keys, resolve_config_path

    argv = list(argv)
    for i, arg in enumerate(argv):
        if arg.startswith("--config="):
            path = resolve_config_path(arg.split("=", 1)[1], ROOT / "configs")
            argv[i] = f"--config={path}"
            break
        if arg == "--config" and i + 1 < len(argv):
            path = resolve_config_path(argv[i + 1], ROOT / "configs")
            argv[i + 1] = str(path)
            break
    else:
        return argv
    check_override_keys(runpy.run_path(str(path))["get_config"](), argv)
    return argv


def main(argv):
    del argv
    from dear_jax import console
    from dear_jax.lock import WorkdirLock, WorkdirLocked

    config_path = flags.FLAGS["config"].config_filename
    workdir = _WORKDIR.value or str(pathlib.Path("runs") / pathlib.Path(config_path).stem)
    try:
        lock = WorkdirLock(workdir)
        lock.acquire()  # before the slow imports: a second run on a workdir fails at once
    except WorkdirLocked as e:
        sys.exit(f"error: {e}")
    console.setup(workdir, verbose=_VERBOSE.value)
    from dear_jax.checkpoint import IncompatibleCheckpointError
    from dear_jax.replay_disk import DiskSpaceError
    from dear_jax.signals import Stopped
    from dear_jax.train import train

    try:
        train(_CONFIG.value, workdir)
    except Stopped as e:
        logging.getLogger("dear_jax").warning("%s", e)
        sys.exit(e.exit_code)
    except (IncompatibleCheckpointError, DiskSpaceError) as e:  # the message says what to do
        logging.getLogger("dear_jax").error("error: %s", e)
        sys.exit(2)
    finally:
        lock.release()


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    try:
        sys.argv[1:] = _resolve_argv(sys.argv[1:])
    except (KeyError, FileNotFoundError) as e:
        sys.exit(f"error: {e.args[0]}")
    app.run(main)
