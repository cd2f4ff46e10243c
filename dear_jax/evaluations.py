"""The training loop's evaluations: when one is due, starting it (in a background thread while
training goes on, or at once), and logging each one's row when it has ended, in order.

Background evaluations run one at a time per evaluator (the run's evaluation processes side by
side, N = `experiment.eval_processes`: the one of index frame // eval_every_frames mod N), in
order, and queue: the loop waits only when MAX_PENDING_EVALS + N - 1 are already started and
not logged, so one evaluation that outlasts the training between two of them does not stall the
loop. Each still evaluates the
parameters of its own frame, on its evaluator's next episodes, as it would unqueued. Evaluations
draw from their own stream of keys (one per frame), so how often a run evaluates never changes
its training.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from dear_jax.carry import Carry
from dear_jax.devices import Hosts
from dear_jax.evaluator import EvalAborted, EvalProcess, EvalProcesses, LocalEvaluator
from dear_jax.logger import RunLogger
from dear_jax.progress import Progress

log = logging.getLogger("dear_jax")

# Background evaluations started and not yet logged before the loop waits for the oldest: two
# absorb one that outlasts the training between two (on an H100 an evaluation of the DrQ-v2
# learning check takes about as long as that training, benchmarks/RESULTS.md), and a stop still
# waits for at most two evaluations before its checkpoint (one more per further evaluation
# process, `experiment.eval_processes`).
MAX_PENDING_EVALS = 2


def eval_due(carry: Carry, total_frames: int) -> bool:
    """An evaluation is due at the carry's frame and has not started."""
    lv, frame = carry.lv, carry.counters["frame"]
    due = frame >= lv["next_eval"] or frame >= total_frames
    return due and lv["last_eval_frame"] != frame


class Evaluations:
    """The queue of evaluations started and not yet logged, oldest first. `background`: in a
    thread of their own per evaluator slot (`config.eval_in_background`; one process only:
    several processes must issue their programs in the same order); else each runs when it is
    started."""

    def __init__(
        self,
        evaluator: LocalEvaluator | EvalProcess | EvalProcesses,
        carry: Carry,
        *,
        hosts: Hosts,
        key: jax.Array,
        background: bool,
        total_frames: int,
        every_frames: int,
        videos: pathlib.Path | None,
        lane_names: list[str],
        num_lanes: int,
        logger: RunLogger,
        progress: Progress,
    ):
        self.evaluator, self.carry, self.hosts, self.key = evaluator, carry, hosts, key
        self.total_frames, self.every_frames = total_frames, every_frames
        self.videos, self.lane_names, self.num_lanes = videos, lane_names, num_lanes
        self.logger, self.progress = logger, progress
        self.pending: collections.deque[dict] = collections.deque()
        self.closing = False  # the loop has ended: evaluations still in this process abort
        # One thread per evaluator: each runs its evaluations in the order they were started.
        self.threads = (
            [
                concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"eval{i}")
                for i in range(evaluator.slots)
            ]
            if background
            else None
        )
        self.max_pending = MAX_PENDING_EVALS + evaluator.slots - 1

    @property
    def beside_training(self) -> bool:
        """An evaluation runs in the background on the training's devices (not in a process of
        its own), its steps' programs queued among the training's."""
        return (
            bool(self.pending)
            and self.threads is not None
            and isinstance(self.evaluator, LocalEvaluator)
        )

    def start_if_due(self, wall_s: float, stop) -> None:
        """Start the evaluation due at this frame, if any: in the background on a copy of the
        parameters while training goes on, or now. Its row is logged by `finish`, with the frame
        and wall time at which it fell due, and the time the loop was held up before going on
        (`loop_wait_s`: waiting for earlier evaluations to end, and in the foreground this one)."""
        self.finish()
        lv, frame = self.carry.lv, self.carry.counters["frame"]
        if not eval_due(self.carry, self.total_frames) or stop:
            return
        background = self.threads is not None
        held = time.perf_counter()
        self.finish(keep=self.max_pending - 1 if background else 0)
        # Which evaluator: from the frame, so that a resumed run evaluates where it would have.
        slot = frame // self.every_frames % self.evaluator.slots
        evaluator = self.evaluator.evaluator_for(slot)
        # A copy: the loop donates the agent's buffers to its next update.
        params = self.carry.agent.params
        params = jax.tree.map(jnp.copy, params) if background else params
        key = self.hosts.env_key(jax.random.fold_in(self.key, frame))
        videos = None
        if self.videos is not None:
            videos = [self.videos / f"eval_{frame}_{name}.mp4" for name in self.lane_names]

        def run():
            t0 = time.perf_counter()
            # A stop cuts short an evaluation that holds up the loop; those in the background
            # (or in their own process) run to their end first, so the checkpoint after them
            # holds their rows. A loop that fails ends those in this process (`closing`).
            abort = (lambda: self.closing) if background else (lambda: bool(stop))
            metrics = evaluator.evaluate(params, key, videos=videos, stop=abort)
            return metrics, time.perf_counter() - t0

        pending = {"frame": frame, "wall_s": wall_s}
        if not background:  # what an aborted evaluation restores (the queue is empty here)
            pending["env_state"] = self.evaluator.host_state()
            pending["loop"] = {k: lv[k] for k in ("last_eval_frame", "next_eval")}
        lv["last_eval_frame"] = frame
        lv["next_eval"] = (frame // self.every_frames + 1) * self.every_frames
        if background:
            pending["future"] = self.threads[slot].submit(run)
        else:
            pending["future"] = future = concurrent.futures.Future()
            try:
                future.set_result(run())
            except EvalAborted as e:
                future.set_exception(e)
        pending["loop_wait_s"] = time.perf_counter() - held
        self.pending.append(pending)
        self.finish(keep=None if background else 0)

    def finish(self, *, keep: int | None = None) -> None:
        """Log the evaluations that have ended, oldest first; with `keep`, first wait until at
        most `keep` are left unlogged."""
        queue = self.pending
        while queue and (queue[0]["future"].done() or (keep is not None and len(queue) > keep)):
            self._log(queue.popleft())

    def _log(self, pending: dict) -> None:
        frame = pending["frame"]
        try:
            metrics, eval_s = pending["future"].result()
        except EvalAborted:  # the resumed run evaluates from here again
            self.evaluator.set_host_state(pending["env_state"])
            self.carry.lv.update(pending["loop"])
            return
        fps_per_seed = frame / pending["wall_s"] if frame else np.nan  # nothing trained at 0
        metrics.update(
            wall_s=pending["wall_s"],
            eval_s=eval_s,
            loop_wait_s=pending["loop_wait_s"],
            fps=fps_per_seed * self.num_lanes,
            sec_per_1000_frames=1000.0 / fps_per_seed,
        )
        self.logger.write("eval", frame, metrics)
        self.progress.last_eval_return = float(np.mean(metrics["episode_return"]))
        log.info(
            "eval @ %s frames: return per seed %s%s",
            f"{frame:,}",
            [round(float(r), 1) for r in metrics["episode_return"]],
            f", success per seed {np.round(metrics['success'], 2).tolist()}"
            if "success" in metrics
            else "",
        )
        self.progress.show_rate(metrics["fps"])

    def close(self) -> None:
        """After the loop (also after a failure): no evaluation in this process is left running
        on the env the run closes next: it aborts at its next step. (The evaluation process's
        `close` waits for the child instead.)"""
        if self.threads is not None:
            self.closing = True
            local = isinstance(self.evaluator, LocalEvaluator)
            for thread in self.threads:
                thread.shutdown(wait=local, cancel_futures=True)
