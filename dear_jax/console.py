"""What a run prints, and the log file that keeps everything.

Console: the progress bar, this project's INFO lines (start, resume, one line per evaluation,
stops) and any library's warnings and errors. Libraries' INFO lines (orbax's dozens per
checkpoint, absl, jax's backend probing, the import notes of optional backends) go only to
`<workdir>/log.txt`, unless `verbose`. Console lines are written through tqdm, so they never
break the bar. A record logged with `extra={"console": False}` goes to the file only.
"""

from __future__ import annotations

import logging
import os
import pathlib
import sys

OURS = ("dear_jax", "envs", "__main__")
LOG_FILE = "log.txt"
_FORMAT = "%(asctime)s %(levelname).1s %(name)s: %(message)s"


class _ConsoleFilter(logging.Filter):
    def __init__(self, verbose: bool):
        super().__init__()
        self.verbose = verbose

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, "console", True):
            return False
        if record.levelno >= logging.WARNING or self.verbose:
            return True
        return record.name.split(".")[0] in OURS and record.levelno >= logging.INFO


class _TqdmHandler(logging.StreamHandler):
    """Writes above an active tqdm bar (tqdm.write), or plainly when there is none."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # noqa: BLE001 - logging must not raise
            self.handleError(record)


def setup(workdir: str | os.PathLike | None, *, verbose: bool = False, process: int = 0) -> None:
    """Route logging as the module docstring says (replaces the root logger's handlers); process
    `process` > 0 of a multi-host run writes `log.<process>.txt`."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    root.setLevel(logging.INFO)
    console = _TqdmHandler(sys.stderr)
    console.setFormatter(logging.Formatter("%(message)s"))
    console.addFilter(_ConsoleFilter(verbose))
    root.addHandler(console)
    if workdir is not None:
        path = pathlib.Path(workdir)
        path.mkdir(parents=True, exist_ok=True)
        name = LOG_FILE if process == 0 else f"log.{process}.txt"
        file = logging.FileHandler(path / name)
        file.setFormatter(logging.Formatter(_FORMAT))
        root.addHandler(file)
    logging.captureWarnings(True)
    try:  # absl (orbax logs through it) keeps its own level and may hold a handler of its own
        from absl import logging as absl_logging

        absl_logging.set_verbosity(absl_logging.INFO)
        absl_logging.get_absl_logger().propagate = True
        absl_handler = absl_logging.get_absl_handler()
        if absl_handler in root.handlers:
            root.removeHandler(absl_handler)
    except ImportError:
        pass
