"""Which CPUs the stack's processes may run on (``skyloop up --pin``).

In lockstep one control step is a serial chain of processes: the sim publishes the scan,
perception reduces it, the policy answers, the bridge hands the setpoint back to the sim
(each hop through the router with ``--router``), and each waits for the one before.
Nothing in the chain runs beside anything else of the chain, so the chain gains nothing
from a second core; what it loses when the scheduler spreads it is a cross-core wake-up
and a cold cache at every hop. With :func:`plan` the chain shares one core (the scan
stays in its caches from hop to hop); everything else (recorder, viewer, the launcher,
whatever else runs) stays free to run anywhere, so it takes the other cores while the
chain runs and the chain's core while the chain waits. Measured (``skyloop bench --only
stack``, ``benchmarks/RESULTS.md`` 2026-12-06, 2 cores, against ``--pin off`` in the same
run): lockstep 281 vs 276 and 309 vs 304 control steps/s in two hours, with the recorder
and ``--pin chain`` 259 vs 243 and 290 vs 269; every chain node's CPU per step 10-30%
lower. Confining the recorder to the other cores as well gained another 0-2% and starved
it behind other work on a loaded machine, so it is not done.

``auto`` pins in lockstep without a recorder or viewer beside the chain. In real time
each node idles most of a step, and the pinned chain's p99 latency fell (8.8-9.0 -> 4.9-6.5
ms) while its p50 rose (3.3 -> 3.7 ms) in the same measurement, so the scheduler keeps the
choice there. With a recorder, a pinned lockstep chain keeps its core busy all the time,
so on a 2-core machine with other work the recorder gets what is left of one core: in a
full test run beside a second test worker it fell behind and dropped 469 messages
(counted), one episode's START and END among them; unpinned it keeps up. So ``auto``
leaves a recorded or viewed run to the scheduler; ``--pin chain`` pins it anyway (7-15%
faster with nothing else at normal priority).

Linux only (``os.sched_setaffinity``); elsewhere, or with fewer than two usable cores,
nothing is pinned. The chain goes to a core the launcher may use itself, so several
stacks on one machine each get their own with ``taskset``
(``taskset -c 0,1 skyloop up ...`` and ``taskset -c 2,3 skyloop up ...``); without it
every stack's chain would take the same highest-numbered core.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

__all__ = ["CHAIN", "Placement", "PinMode", "plan"]

#: the processes one lockstep step passes through, in order (the router relays every hop)
CHAIN = ("sim", "perception", "policy", "bridge", "router")
PinMode = Literal["auto", "chain", "off"]


@dataclass(frozen=True)
class Placement:
    """The chain's CPUs; the other nodes are not pinned."""

    chain: frozenset[int]

    def cpus(self, node: str) -> frozenset[int] | None:
        """The CPUs ``node`` is pinned to (None: not pinned)."""
        return self.chain if node in CHAIN else None


def plan(pin: PinMode, lockstep: bool, beside: bool = False,
         allowed: set[int] | None = None) -> Placement | None:
    """Where the chain goes, or None to leave it to the scheduler: with ``pin`` "chain"
    (or "auto" in lockstep with nothing ``beside`` the chain: no recorder, no viewer) and
    at least two of the ``allowed`` CPUs (default: this process's), the highest-numbered
    one (CPU 0 tends to take more of the machine's interrupts)."""
    if pin == "off" or (pin == "auto" and (not lockstep or beside)):
        return None
    if allowed is None:
        if not hasattr(os, "sched_getaffinity"):
            return None
        allowed = os.sched_getaffinity(0)
    if len(allowed) < 2:
        return None
    return Placement(frozenset({max(allowed)}))

