"""SIGTERM, SIGINT (Ctrl-C) and SIGHUP (a closed terminal) ask a run to stop: it checkpoints at the
end of its current step and exits.

`StopRequest` replaces their handlers while a run lasts (main thread only; elsewhere it does
nothing) and restores the previous ones after; a SIGHUP the process started ignoring (`nohup`)
stays ignored. The first signal only sets a flag that the loop
reads once per step (and every step of an evaluation); a second one stops at once with
StoppedAtOnce (a KeyboardInterrupt), without a checkpoint (the previous checkpoint stays intact: saves are atomic).
"""

from __future__ import annotations

import signal
import threading

from envs.forkserver import STOP_SIGNALS as SIGNALS


class Stopped(Exception):
    """The run stopped on a signal after saving a checkpoint; `signum` says which signal."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # what a shell reports for a process ended by that signal


class StoppedAtOnce(KeyboardInterrupt):
    """A second signal stopped the run at once, without a checkpoint."""

    def __init__(self, signum: int):
        super().__init__(f"a second {signal.Signals(signum).name}: stopped at once")
        self.signum = signum


class StopRequest:
    """Context manager: `signum` is None until a stop signal (`SIGNALS`) arrives."""

    def __init__(self):
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def __bool__(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else ""

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:
            raise StoppedAtOnce(signum)
        self.signum = signum

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
