"""TD3's update in two threads: the next mini-batch's TD target while this one learns
(``TargetPipeline``, ``--pipeline target``), or the targets, actor steps and soft updates
beside the critic steps (``SplitLearner``, ``--pipeline actor``).

One update of ``policy.algorithms.td3.TD3`` is three parts in order: the target y of
eqs. 2.11-2.12 (forward passes of the *target* networks only, about a quarter of the
work), the critic and delayed actor gradient steps (``TD3.learn``), and on delayed steps
the soft target update (``TD3.update_targets``). ``TargetPipeline`` computes the target
of update k+1 in a worker thread while the calling thread runs the gradient steps of
update k::

    caller:  sample B_{k+1} -> worker | learn(B_k, y_k) | [wait worker; soft update] | ...
    worker:                            y_{k+1} = target(B_{k+1})                      |

The worker reads the target networks and the agent's target-noise generator, nothing
else; the caller writes the target networks only while the worker is idle, so no tensor
is read while written. The one difference from ``TD3.update``: y_{k+1} is computed
before, not after, the soft update of step k (delayed steps only), so on half the
updates the target networks lag by one soft update (tau = 0.005 of the way). The
mini-batches are sampled by the caller, in the same order, so the replay buffer stays
single-threaded.

torch releases the GIL inside its kernels, so with one torch thread per Python thread
(``torch.set_num_threads(1)``) the two run on two cores without OpenMP barriers between
them. Beside a collector process on a 2-core machine that gained 10-13% in two
benchmark runs and lost 17-22% in a third, when the host took part of the CPU
(``benchmarks/RESULTS.md``, issue 9). Deterministic given the mini-batches (each tensor
has one writer at a time; tests/test_pipeline.py checks the schedule bit for bit); the
parallel training mode as a whole is not (the collector's timing); ``--sync`` never
uses it.
"""

from __future__ import annotations

import copy
import queue
import threading
from collections.abc import Callable

import torch

from policy.algorithms.replay import Batch
from policy.algorithms.td3 import TD3, LowPrecisionCopy

__all__ = ["SplitLearner", "TargetPipeline"]

_STOP = object()


class TargetPipeline:
    """``update()`` is ``agent.update(sample())`` with the target computed one update ahead
    in a worker thread (module docstring). ``settle()`` before reading the agent's state
    (a checkpoint); ``close()`` at the end (also a context manager)."""

    def __init__(self, agent: TD3, sample: Callable[[], Batch],
                 flush_denormals: bool = True) -> None:
        self.agent, self.sample = agent, sample
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._done: queue.Queue = queue.Queue(maxsize=1)
        self._ready: tuple[Batch, torch.Tensor] | None = None  # the next update's
        self._busy = False  # the worker has a job whose result is not taken yet
        self._worker = threading.Thread(target=self._work, args=(flush_denormals,),
                                        name="skyloop-td-target", daemon=True)
        self._worker.start()

    def _work(self, flush: bool) -> None:
        torch.set_flush_denormal(flush)  # per thread (policy.algorithms.td3.flush_denormals)
        while (batch := self._jobs.get()) is not _STOP:
            try:
                with torch.no_grad():
                    y = self.agent.target(batch.next_state, batch.reward, batch.done)
                self._done.put((batch, y))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller, re-raised
                self._done.put(exc)

    def _submit(self) -> None:
        self._jobs.put(self.agent.to_device(self.sample()))
        self._busy = True

    def settle(self) -> None:
        """Wait until the worker is idle (its result kept for the next update)."""
        if self._busy:
            result = self._done.get()
            self._busy = False
            if isinstance(result, BaseException):
                raise result
            self._ready = result

    def update(self, train_actor: bool = True) -> dict[str, float]:
        """One update of Algorithm 3.1 on the next mini-batch; returns the losses."""
        if self._ready is None:
            if not self._busy:
                self._submit()
            self.settle()
        batch, y = self._ready
        self._ready = None
        self._submit()  # the next target, while this thread learns
        out = self.agent.learn(batch, y, train_actor)
        if self.agent.delayed_step():
            self.settle()  # the worker reads the target networks: done before writing
            self.agent.update_targets()
        return out

    def close(self) -> None:
        """Stop the worker (a pending result is dropped)."""
        if not self._worker.is_alive():
            return
        try:
            self.settle()
        finally:
            self._jobs.put(_STOP)
            self._worker.join()

    def __enter__(self) -> TargetPipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SplitLearner:
    """TD3's update in two threads, the actor's work in the second: the caller takes only
    the critic steps; a worker takes the TD targets, the delayed actor steps and the soft
    target updates.

    Per update k the caller keeps ``AHEAD`` target jobs queued (sampling their
    mini-batches in order), waits for y_k, takes the critic step (eq. 2.13) and, on a delayed step,
    copies the critic (``snapshot``) and queues the actor job: the deterministic policy
    gradient through the snapshot's Q_1 (exactly Q_1 after critic step k, as in TD3), then
    theta' <- tau theta + (1 - tau) theta' for the actor and, from the snapshot, the
    critics. The worker runs its jobs in order, so the actor step of k runs beside the
    critic steps of k+1 and k+2. Differences from ``TD3.update``: a target may be computed
    up to one soft update early (as in ``TargetPipeline``), and the collector gets the
    actor from ``on_actor`` in the worker, after its soft update, instead of from the
    caller. ``settle()`` waits until the worker is idle (checkpoints).

    Deterministic: each tensor has one writer, and the worker runs its jobs in the order
    queued, so every job sees the same state whatever the timing; the result is that of
    ``TD3.update`` with each target computed ``AHEAD`` mini-batches early
    (tests/test_pipeline.py checks it bit for bit).
    """

    AHEAD = 3  # targets queued ahead, so that a critic step does not wait for its y

    def __init__(self, agent: TD3, sample: Callable[[], Batch],
                 on_actor: Callable[[torch.nn.Module], None] | None = None,
                 flush_denormals: bool = True) -> None:
        self.agent, self.sample, self.on_actor = agent, sample, on_actor
        self.snapshot = copy.deepcopy(agent.critic).requires_grad_(False)
        self._snap_lp = LowPrecisionCopy(self.snapshot, agent.dtype)
        self._snap = list(self.snapshot.parameters())
        self._jobs: queue.Queue = queue.Queue()
        self._done: queue.Queue = queue.Queue()
        self._targets = 0  # target jobs queued whose y is not taken yet
        self._actor_free = threading.Event()  # no actor job queued or running
        self._actor_free.set()
        self.actor_loss: float | None = None
        self._error: BaseException | None = None
        self._worker = threading.Thread(target=self._work, args=(flush_denormals,),
                                        name="skyloop-actor-target", daemon=True)
        self._worker.start()

    # -- the worker ------------------------------------------------------------------

    def _work(self, flush: bool) -> None:
        torch.set_flush_denormal(flush)
        while (job := self._jobs.get()) is not _STOP:
            kind, payload = job
            try:
                if kind == "target":
                    with torch.no_grad():
                        y = self.agent.target(payload.next_state, payload.reward,
                                              payload.done)
                    self._done.put((payload, y))
                else:
                    self._actor_step(payload)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller, re-raised
                if kind == "target":
                    self._done.put(exc)
                else:
                    self._error = exc
            finally:
                if kind == "actor":
                    self._actor_free.set()
                self._jobs.task_done()
        self._jobs.task_done()

    def _actor_step(self, state: torch.Tensor | None) -> None:
        """The delayed actor step on ``state`` (None: none, a critic warm-up) through the
        snapshot's Q_1, then the soft target updates; hands the actor to ``on_actor``."""
        a = self.agent
        if state is not None:
            self._snap_lp.changed()  # the snapshot was just written
            self.actor_loss = a.actor_step(state, self._snap_lp.net())
        a.update_targets(critic=self._snap)  # the critics' theta: Q after critic step k
        if self.on_actor is not None:
            self.on_actor(a.actor)

    # -- the caller ------------------------------------------------------------------

    def _raise(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def _queue_target(self) -> None:
        self._jobs.put(("target", self.agent.to_device(self.sample())))
        self._targets += 1

    def update(self, train_actor: bool = True) -> dict[str, float]:
        """One update of Algorithm 3.1 (its actor part handed to the worker)."""
        self._raise()
        while self._targets < self.AHEAD:
            self._queue_target()
        result = self._done.get()
        self._targets -= 1
        if isinstance(result, BaseException):
            raise result
        batch, y = result
        a = self.agent
        out = a.learn(batch, y, train_actor=False)  # the critic step
        if a.delayed_step():
            self._actor_free.wait()  # its last job read the snapshot and the actor
            self._raise()
            torch._foreach_copy_(self._snap, list(a.critic.parameters()))
            self._actor_free.clear()
            self._jobs.put(("actor", batch.state.to(a.dtype) if train_actor else None))
        if self.actor_loss is not None:
            out["actor_loss"] = self.actor_loss
        return out

    def settle(self) -> None:
        """Wait until the worker has done every queued job (their targets are kept)."""
        self._jobs.join()
        self._raise()

    def close(self) -> None:
        if not self._worker.is_alive():
            return
        self._jobs.put(_STOP)
        self._worker.join()
        self._raise()

    def __enter__(self) -> SplitLearner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
