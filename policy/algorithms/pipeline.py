"""TD3's update in two threads: the next mini-batch's TD target while this one learns
(``TargetPipeline``, ``--pipeline target``).

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
has one writer at a time; tests/policy/test_pipeline.py checks the schedule bit for bit); the
parallel training mode as a whole is not (the collector's timing); ``--sync`` never
uses it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

import torch

from policy.algorithms.replay import Batch
from policy.algorithms.td3 import TD3

__all__ = ["TargetPipeline"]

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
