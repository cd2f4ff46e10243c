"""SIGTERM, SIGINT (Ctrl-C) and SIGHUP (a closed terminal) ask a run to stop: it checkpoints at the
end of its current step and exits.

`StopRequest` replaces their handlers while a run lasts (main thread only; elsewhere it does
nothing) and restores the previous ones after; a SIGHUP the process started ignoring (`nohup`)
stays ignored. The first signal says so on stderr at once and sets a flag that the run reads
between the stages of its start (`before_training`: nothing trained, nothing saved) and the loop
once per step (and every step of an evaluation); a second one stops at once with StoppedAtOnce
(a KeyboardInterrupt), without a checkpoint (the previous checkpoint stays intact: saves are
atomic). A signal within REPEAT_WINDOW_S of the first is the same request: `timeout`, for one,
sends its SIGTERM to the process and then to its process group, which holds the process too.
"""

from __future__ import annotations

import os
import signal
import threading
import time

from envs.forkserver import STOP_SIGNALS as SIGNALS

# Seconds after the first stop signal in which another is taken as its repeat, not as a second.
REPEAT_WINDOW_S = 1.0


class Stopped(Exception):
    """The run stopped on a signal after saving a checkpoint; `signum` says which signal."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # what a shell reports for a process ended by that signal


class StoppedBeforeTraining(Stopped):
    """The run stopped on a signal before its first step: nothing was trained or saved."""


def before_training(stop, saved_frame: int | None) -> None:
    """Raises StoppedBeforeTraining once `stop` (a StopRequest) holds a signal: called between the
    stages of a run's start. saved_frame: the frame of the checkpoint a resumed run started from,
    which stays (None: a new run)."""
    if stop:
        kept = "" if saved_frame is None else f" (the checkpoint at frame {saved_frame:,} stays)"
        raise StoppedBeforeTraining(
            f"stopped by {stop.name} before training began; nothing was saved{kept}", stop.signum
        )


class StoppedAtOnce(KeyboardInterrupt):
    """A second signal stopped the run at once, without a checkpoint."""

    def __init__(self, signum: int):
        super().__init__(f"a second {signal.Signals(signum).name}: stopped at once")
        self.signum = signum


class StopRequest:
    """Context manager: `signum` is None until a stop signal (`SIGNALS`) arrives."""

    def __init__(self):
        self.signum: int | None = None
        self._first_at = 0.0  # time.monotonic() of the first signal
        self._previous: dict[int, object] = {}

    def __bool__(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:
            if time.monotonic() - self._first_at < REPEAT_WINDOW_S:
                return  # the first's repeat (a signal to the process and to its group)
            raise StoppedAtOnce(signum)
        self.signum, self._first_at = signum, time.monotonic()
        name = signal.Signals(signum).name
        # At once (a start or a step may take a while), and not through `logging`, whose lock
        # the interrupted code may hold.
        try:
            os.write(2, f"{name} received: stopping (a second {name} stops at once)\n".encode())
        except OSError:  # stderr gone (a closed terminal, a pipe's reader ended): stop all the same
            pass

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                if (
                    sig == getattr(signal, "SIGHUP", None)
                    and signal.getsignal(sig) == signal.SIG_IGN
                ):
                    continue  # nohup's: the run outlives its terminal
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}


class AgreedStop:
    """A StopRequest as several processes read it: set by the loop's step (`dear_jax/loop.py`)
    once any process got a signal (`request`: this process's own), on every process at the same
    step, so that all checkpoint together."""

    def __init__(self, request: StopRequest):
        self.request, self.signum = request, None

    def __bool__(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""
