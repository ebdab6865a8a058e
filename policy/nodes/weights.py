"""Actor weights over the bus (topic ``actor``, ``skyloop_msgs/ActorWeights``).

The blob is what :meth:`policy.algorithms.td3.TD3.save_actor` writes (``torch.save`` of the format
tag ``skyloop-actor-1``, the actor's shape config and its state dict), the message
``format`` is that tag and ``sha256`` the blob's hex digest. Versions count up from 1
per learner run; version 0 is whatever actor a policy node started with.

:class:`WeightsFollower` is the policy node's side: the Zenoh callback only keeps the
newest message (no decoding there); :meth:`WeightsFollower.poll` (main loop) decodes
and checks it and *holds* the new actor; :meth:`WeightsFollower.at_episode_boundary`
swaps it in, so an episode is always flown by one actor. A blob that does not decode,
has another format or digest, other layer shapes or non-finite weights is rejected
(counted by reason, logged); the actor in use keeps flying.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import threading
from collections.abc import Callable
from typing import Any

import torch

from bus import keys
from bus import messages as m
from bus.task import TASK
from policy.algorithms.networks import Actor
from policy.algorithms.td3 import ACTOR_FORMAT, TD3, load_actor

log = logging.getLogger("skyloop.policy.nodes.weights")
WEIGHTS_LINE = "SKYLOOP-POLICY-WEIGHTS "


class WeightsRejected(ValueError):
    """An ``ActorWeights`` message that cannot replace the actor in use: ``kind`` (format,
    sha256, decode, shapes, non-finite) and the message say why."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind


def encode_actor(agent: TD3) -> bytes:
    """The agent's actor as the blob :func:`decode_actor` reads."""
    buf = io.BytesIO()
    agent.save_actor(buf)
    return buf.getvalue()


def actor_weights_message(agent: TD3, version: int, stamp_s: float = 0.0) -> Any:
    """``ActorWeights`` of ``agent``'s actor with ``version``, format and digest."""
    blob = encode_actor(agent)
    return m.actor_weights(blob, version, stamp_s, fmt=ACTOR_FORMAT,
                           sha256=hashlib.sha256(blob).hexdigest())


def decode_actor(msg: Any, like: Actor) -> Actor:
    """The actor of an ``ActorWeights`` message, checked against ``like`` (the actor in
    use: same layer shapes and action bound); ``WeightsRejected`` says why not."""
    if msg.format != ACTOR_FORMAT:
        raise WeightsRejected("format", f"{msg.format!r}, expected {ACTOR_FORMAT!r}")
    blob = m.actor_blob(msg)
    if msg.sha256 and hashlib.sha256(blob).hexdigest() != msg.sha256:
        raise WeightsRejected("sha256", "the digest does not match the blob")
    try:
        actor = load_actor(io.BytesIO(blob), task=TASK)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for bad bytes
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise WeightsRejected("decode", f"the blob does not decode ({first})") from None
    want = {k: tuple(v.shape) for k, v in like.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in actor.state_dict().items()}
    if got != want or actor.max_action != like.max_action:
        raise WeightsRejected("shapes", f"layers {sorted(got.values())} (max_action "
                              f"{actor.max_action}) do not match the actor in use "
                              f"{sorted(want.values())} (max_action {like.max_action})")
    if not all(bool(torch.isfinite(p).all()) for p in actor.parameters()):
        raise WeightsRejected("non-finite", "NaN or infinite weights")
    return actor


class WeightsFollower:
    """Follows ``skyloop/<vehicle>/actor`` for a controller with an ``actor`` attribute
    (see the module docstring). ``emit`` gets one ``WEIGHTS_LINE`` JSON line per swap."""

    def __init__(self, bus: Any, vehicle: str, controller: Any,
                 emit: Callable[[str], None] | None = None) -> None:
        if not isinstance(getattr(controller, "actor", None), Actor):
            raise ValueError("--weights-from-bus needs an actor policy (not 'scripted')")
        self.controller, self.vehicle, self.emit = controller, vehicle, emit
        self.version = 0  # in use
        self.held: tuple[int, Actor] | None = None
        self.received = self.stale = self.swaps = 0
        self.rejected: dict[str, int] = {}
        self.history: list[dict] = []  # one entry per swap
        self._newest = 0
        self._incoming: Any = None
        self._lock = threading.Lock()
        self.subscription = bus.subscribe(keys.ACTOR, vehicle, self._on_message)

    def _on_message(self, msg: Any) -> None:  # Zenoh thread: keep the newest, no work
        with self._lock:
            self.received += 1
            if int(msg.version) <= self._newest:
                self.stale += 1
                return
            self._newest = int(msg.version)
            self._incoming = msg

    def reject(self, version: int, err: WeightsRejected) -> None:
        self.rejected[err.kind] = self.rejected.get(err.kind, 0) + 1
        log.warning("actor version %d rejected (%s); version %d keeps flying", version, err,
                    self.version)

    def poll(self) -> None:
        """Decode and check the newest message, if any, and hold it for the next
        episode boundary (main loop; a few ms for a 400-300 actor)."""
        with self._lock:
            msg, self._incoming = self._incoming, None
        if msg is None:
            return
        try:
            actor = decode_actor(msg, self.controller.actor)
        except WeightsRejected as exc:
            self.reject(int(msg.version), exc)
            return
        self.held = (int(msg.version), actor)
        log.info("actor version %d received; flying it from the next episode", msg.version)

    def at_episode_boundary(self, episode: int) -> int | None:
        """Swap in the held actor (call where the frame stacker resets); its version."""
        if self.held is None:
            return None
        (version, actor), self.held = self.held, None
        self.controller.actor = actor
        old, self.version = self.version, version
        self.swaps += 1
        entry = {"vehicle": self.vehicle, "version": version, "previous": old,
                 "episode": episode, "swaps": self.swaps}
        self.history.append(entry)
        log.info("actor version %d in use from episode %d (was %d; swap %d)", version,
                 episode, old, self.swaps)
        if self.emit is not None:
            self.emit(WEIGHTS_LINE + json.dumps(entry))
        return version

    def counters(self) -> dict[str, Any]:
        return {"version": self.version, "received": self.received, "stale": self.stale,
                "swaps": self.swaps, "rejected": dict(self.rejected)}
