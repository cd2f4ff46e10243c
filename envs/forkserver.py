"""The fork server that starts the render workers and the evaluation processes.

Neither may be forked from a process that holds JAX's or CUDA's threads, so both come from
multiprocessing's fork server, started once per process with their modules imported: `context`
gives its context. The stop signals (`STOP_SIGNALS`) are the training process's to handle: it
lets the evaluation in flight end, then checkpoints. Its helpers never see them: the fork server
and multiprocessing's resource tracker start with them blocked (and keep them blocked; the fork
server's children inherit that), and the children ignore them (`ignore_stop_signals`). A signal
to the whole process group (`timeout`, a cluster's stop, `kill -- -PGID`, a closed terminal)
that killed the fork server would make its children, still at work, read as dead (exit code
255); one that killed the resource tracker would leave its warnings and leaks. Both still end
when the last process that uses them does.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver
import signal
from multiprocessing import resource_tracker

STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name)
)


def ignore_stop_signals() -> None:
    """In a helper process of a training process: leave the stop signals to the latter."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def context(*preload: str) -> multiprocessing.context.ForkServerContext:
    """The forkserver context, its server (when this call starts it) importing `preload`."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(preload))
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, ())  # a signal here waits till restored
    try:
        # Blocked anew for each: the tracker's start unblocks SIGINT and SIGTERM here after it.
        for start in (resource_tracker.ensure_running, multiprocessing.forkserver.ensure_running):
            signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
            start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    return ctx
