"""Train DEAR or a baseline: `python run.py --config walker_dear.py [--workdir DIR]`.

`--config` takes a file path or a bare name of a file in configs/, with an optional config
string after a colon (`--config paper.py:cup,sear,hard`). Any config field can be
overridden: `--config.seeds=5 --config.agent.beta=10`. Rerunning the same command on the same
workdir resumes from its latest checkpoint. SIGTERM, Ctrl-C or SIGHUP checkpoints, then exits
(with 128 + the signal's number; before training begins, it exits without saving anything, a new
workdir removed; a second signal a second or more after the first stops at once, the last
checkpoint kept);
`--verbose` shows libraries' INFO logs, which otherwise go only to <workdir>/log.txt.

Exit status: 0 trained (or had already); 1 bad input, refused before the run starts (an unknown
field or choice, a missing background folder); 2 refused once started (a resume with a changed
config, an unreadable checkpoint or replay, too little memory or disk); 128 + N stopped by
signal N.

Several hosts: start the same command on each with `--multihost` (README, "Several hosts").
"""

import contextlib
import io
import logging
import os
import pathlib
import runpy
import shutil
import signal
import sys

from absl import app, flags
from ml_collections import config_flags

ROOT = pathlib.Path(__file__).resolve().parent

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "experiment config: a file path, or a bare name of a file in configs/"
)
_WORKDIR = flags.DEFINE_string(
    "workdir",
    None,
    "output folder (default: runs/<config file's stem>[_<its config string's parts>], e.g. "
    "runs/paper_walker_dear_medium); reused to resume",
)
_VERBOSE = flags.DEFINE_bool("verbose", False, "show libraries' INFO logs on the console too")
_MULTIHOST = flags.DEFINE_bool(
    "multihost",
    False,
    "be one process of a multi-host run: jax.distributed.initialize() with JAX_COORDINATOR_ADDRESS, "
    "JAX_NUM_PROCESSES and JAX_PROCESS_ID, or what the cluster says (SLURM...); also on when "
    "JAX_COORDINATOR_ADDRESS is set",
)
flags.mark_flags_as_required(["config"])


def _resolve_argv(argv: list[str]) -> list[str]:
    """argv with --config's bare name made a path; friendly errors for a missing config file or
    an unknown --config.key, before absl parses."""
    from dear_jax.config import check_override_keys, resolve_config_path

    argv = list(argv)
    for i, arg in enumerate(argv):
        if arg.startswith("--config="):
            prefix, value = "--config=", arg.split("=", 1)[1]
            break
        if arg == "--config" and i + 1 < len(argv):
            i, prefix, value = i + 1, "", argv[i + 1]
            break
    else:
        return argv
    name, *spec = value.split(":", 1)  # a config string after the colon goes to get_config
    path = resolve_config_path(name, ROOT / "configs")
    argv[i] = prefix + ":".join([str(path), *spec])
    get_config = runpy.run_path(str(path))["get_config"]
    try:
        config = get_config(*spec)
    except TypeError:
        if not spec:
            raise
        raise ValueError(
            f"{path.name} takes no config string after ':' (paper.py does, e.g. "
            "paper.py:walker,dear)"
        ) from None
    check_override_keys(config, argv)
    return argv


def _start_processes() -> int:
    """jax.distributed.initialize() if asked (before anything touches a device); returns this
    process's index (0 alone)."""
    env = os.environ
    if not (_MULTIHOST.value or env.get("JAX_COORDINATOR_ADDRESS")):
        return 0
    import jax

    number = lambda name: int(env[name]) if env.get(name) else None  # noqa: E731
    jax.distributed.initialize(
        num_processes=number("JAX_NUM_PROCESSES"), process_id=number("JAX_PROCESS_ID")
    )
    return jax.process_index()


def _check(config) -> None:
    """The trainer's checks of a config, its background videos' folder and the runs beside it
    on its GPU ($DEAR_JAX_RUNS_PER_GPU), before the run writes anything."""
    root = logging.getLogger()
    level = root.level
    # Libraries' notes (imports, backends) are for the log; the trainer's warnings come again,
    # in the console's format, when train() checks the config once more.
    root.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            from dear_jax.experiment import validate
            from dear_jax.summary import runs_per_gpu
            from envs.distractions import check_background_dir

            validate(config)
            check_background_dir(config.env)
            runs_per_gpu()  # $DEAR_JAX_RUNS_PER_GPU, as the grid sets it
    finally:
        root.setLevel(level)


def _remove_if_unused(workdir: pathlib.Path) -> None:
    """A workdir this run made and left with nothing but its log and folders without a file (a
    start refused once it had made checkpoints/ and replay/): removed."""
    from dear_jax import console

    entries = list(workdir.iterdir())
    if all(
        p.name == console.LOG_FILE or (p.is_dir() and not any(f.is_file() for f in p.rglob("*")))
        for p in entries
    ):
        for p in entries:
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink()
        workdir.rmdir()


def _leave(workdir: pathlib.Path, lock, new: bool, unstarted: bool, refused: bool) -> None:
    """The workdir as a run leaves it: a new one stopped before training emptied (nothing in it is
    worth keeping), a new one emptied or refused removed where nothing else is left; the lock
    released."""
    if unstarted and new:
        logging.shutdown()
        for path in workdir.iterdir():  # but the lock, held until the folder is empty
            if path.is_dir():
                shutil.rmtree(path)
            elif path != lock.path:
                path.unlink()
    lock.release()
    if (refused or unstarted) and new:
        _remove_if_unused(workdir)  # refused before it wrote anything else


# What a stop signal before training undoes, in order (the workdir's lock, a new workdir).
_UNDO_BEFORE_TRAINING = []
_STOP_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)


def _stop_before_training(signum, frame):
    """Until train() takes the stop signals over (dear_jax/signals.py), SIGINT, SIGTERM or SIGHUP
    (unless ignored, as under nohup) ends the process at once: nothing is trained or saved yet,
    and an interrupt raised during the imports could otherwise be swallowed (a KeyboardInterrupt
    in a garbage-collection callback is only printed, and the run would go on)."""
    for undo in _UNDO_BEFORE_TRAINING:
        undo()
    name = signal.Signals(signum).name
    os.write(2, f"stopped by {name} before training began; nothing was saved\n".encode())
    os._exit(128 + signum)


def main(argv):
    del argv
    from dear_jax import console
    from dear_jax.lock import WorkdirLock, WorkdirLocked

    path, _, spec = flags.FLAGS["config"].config_filename.partition(":")
    name = "_".join([pathlib.Path(path).stem, *filter(None, map(str.strip, spec.split(",")))])
    workdir = _WORKDIR.value or str(pathlib.Path("runs") / name)
    process = _start_processes()
    new = not pathlib.Path(workdir).exists()
    if not new and not pathlib.Path(workdir).is_dir():
        sys.exit(f"error: --workdir {workdir} is a file: give a folder (a new one, or a run's)")
    console.setup(None, verbose=_VERBOSE.value)  # the console's format from here (log.txt: below)
    try:
        lock = WorkdirLock(workdir, process)
        lock.acquire()  # before the slow imports: a second run on a workdir fails at once
    except (WorkdirLocked, OSError) as e:  # in use, or not a folder one can make
        sys.exit(f"error: {e}")
    _UNDO_BEFORE_TRAINING.append(lock.release)
    if new:
        _UNDO_BEFORE_TRAINING.append(lambda: _remove_if_unused(pathlib.Path(workdir)))
    try:
        _check(_CONFIG.value)
    except (ValueError, FileNotFoundError) as e:  # bad input: one line, nothing left behind
        lock.release()
        if new:
            pathlib.Path(workdir).rmdir()  # it holds nothing but the lock this run took
        sys.exit(f"error: {e}")
    except BaseException:
        lock.release()
        raise
    console.setup(workdir, verbose=_VERBOSE.value, process=process)
    from dear_jax.checkpoint import IncompatibleCheckpointError, UnreadableCheckpointError
    from dear_jax.experiment import ConfigError
    from dear_jax.replay_disk import DiskSpaceError, MissingReplayError
    from dear_jax.signals import Stopped, StoppedAtOnce, StoppedBeforeTraining
    from dear_jax.train import train

    for sig in _STOP_SIGNALS:  # train() takes the stop signals over; after it, their defaults
        if signal.getsignal(sig) == _stop_before_training:
            signal.signal(
                sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
            )
    refused = unstarted = False
    try:
        train(_CONFIG.value, workdir)
    except Stopped as e:
        logging.getLogger("dear_jax").warning("%s", e)
        unstarted = isinstance(e, StoppedBeforeTraining)
        sys.exit(e.exit_code)
    except StoppedAtOnce as e:  # saves are atomic: the last checkpoint stays whole
        steps = (pathlib.Path(workdir) / "checkpoints").glob("*")
        saved = [int(p.name) for p in steps if p.name.isdigit()]  # not a save's temporary folder
        logging.getLogger("dear_jax").warning(
            "%s, without a checkpoint; %s",
            e,
            f"the one at frame {max(saved):,} per seed stays: rerun the same command to resume"
            if saved
            else "none was saved before: rerun the same command to start over",
        )
        # Nothing saved or logged (a second signal while a stop before training unwinds): a new
        # workdir goes, as after one signal.
        unstarted = not saved and not any(pathlib.Path(workdir).glob("*/*.csv"))
        logging.shutdown()
        _leave(pathlib.Path(workdir), lock, new, unstarted, refused=False)
        # Cut short inside a compile or a render, the interpreter's shutdown may crash (a
        # segmentation fault, seen); the run's resources were closed as the stop unwound.
        os._exit(128 + e.signum)
    except UnreadableCheckpointError as e:
        logging.getLogger("dear_jax").error("error: %s", e)
        lock.release()
        logging.shutdown()
        # orbax's reads of the damaged files are left pending: at the interpreter's shutdown each
        # would print its own traceback, hundreds of lines below the error. Nothing is left to save.
        os._exit(2)
    except (
        IncompatibleCheckpointError,
        MissingReplayError,
        DiskSpaceError,
        ConfigError,
        MemoryError,
    ) as e:
        logging.getLogger("dear_jax").error("error: %s", e)  # the message says what to do
        refused = True
        sys.exit(2)
    finally:
        _leave(pathlib.Path(workdir), lock, new, unstarted, refused)


if __name__ == "__main__":
    for sig in _STOP_SIGNALS:
        if signal.getsignal(sig) != signal.SIG_IGN:
            signal.signal(sig, _stop_before_training)
    sys.path.insert(0, str(ROOT))
    try:
        sys.argv[1:] = _resolve_argv(sys.argv[1:])
    except (KeyError, FileNotFoundError, ValueError) as e:
        sys.exit(f"error: {e.args[0]}")
    app.run(main)
