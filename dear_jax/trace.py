"""config.profile: a jax.profiler trace of a few iterations of the training loop."""

from __future__ import annotations

import logging
import pathlib

import jax
from ml_collections import ConfigDict

log = logging.getLogger("dear_jax")


class Trace:
    """config.profile: a jax.profiler trace of a few loop iterations, to workdir/profile (with
    several processes, workdir/profile/process_<p>)."""

    def __init__(self, settings: ConfigDict, workdir: pathlib.Path, frame: int):
        self.at, self.left = settings.at_frame, settings.iterations
        self.directory = workdir / "profile"
        if jax.process_count() > 1:
            self.directory = self.directory / f"process_{jax.process_index()}"
        self.on = False
        if self.at < frame:  # off, or a resumed run past the frame: traced before, if ever
            self.left = 0

    def tick(self, frame: int, sync) -> None:
        """Called before each iteration; `sync` waits for the device work dispatched so far."""
        if self.on:
            self.left -= 1
            if not self.left:
                self.stop(sync)
        elif self.left > 0 and self.at <= frame:
            sync()  # the trace starts with an empty queue, so it holds whole iterations
            try:
                jax.profiler.start_trace(str(self.directory))
            except RuntimeError as e:  # e.g. another trace already running in this process
                log.warning("profile not taken: %s", e)
                self.left = 0
                return
            self.on = True

    def stop(self, sync=None) -> None:
        """End the trace; `sync` first waits for the work it covers (None: a run failing)."""
        if self.on:
            self.on, self.left = False, 0
            if sync is not None:
                sync()
            jax.profiler.stop_trace()
            log.info("profile of the loop written to %s (tensorboard --logdir)", self.directory)
