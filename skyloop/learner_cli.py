"""``skyloop learner``: the actor-learner's command line.

Settings are :class:`policy.learner.LearnerConfig`; the node, :mod:`policy.learner_node`,
is imported only when the command runs, so ``skyloop --help`` stays light.

Example: two vehicles' stacks (``skyloop sim/perception/bridge/policy --vehicle uav1``
and ``uav2``, distinct MAVLink ports) and::

    skyloop learner --vehicles uav1 uav2 --algo td3 --reward abr --out runs/learner
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from policy.learner import ALGOS, REWARDS, LearnerConfig
from skyloop.argtypes import add_bus_flags


def cmd_learner(args: argparse.Namespace) -> int:
    from bus.node import Bus
    from bus.session import SessionConfig
    from policy.learner_node import Learner

    config = LearnerConfig(
        vehicles=args.vehicles, algo=args.algo, reward=args.reward, seed=args.seed,
        updates_per_step=args.updates_per_step, warmup=args.warmup,
        critic_warmup=args.critic_warmup,
        publish_every=args.publish_every, checkpoint_every=args.checkpoint_every,
        init_actor=args.init_actor, buffer_size=args.buffer_size,
        max_episodes=args.max_episodes, grace_s=args.grace, threads=args.threads,
        resume=args.resume)
    config.validate()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = Bus.open(SessionConfig.from_flags(args.mode, args.connect, args.listen,
                                               args.zenoh_config))
    try:
        learner = Learner(bus, config, Path(args.out),
                          emit=lambda line: print(line, flush=True))
        summary = learner.run(stop.is_set, progress=not args.no_progress)
    finally:
        bus.close()
    print(f"learner: {summary['episodes']} episodes {summary['by_vehicle']}, "
          f"{summary['updates']} updates, version {summary['version']}, skipped "
          f"{json.dumps(summary['skipped'])}; checkpoint {summary['checkpoint']}",
          file=sys.stderr, flush=True)
    return 0


def add_learner_parser(sub: Any) -> None:
    """Register ``skyloop learner`` on ``sub`` (argparse subparsers)."""
    d = LearnerConfig()
    p = sub.add_parser("learner", help="learn from live episodes on the bus, publish actor "
                                       "weights that 'policy --weights-from-bus' nodes fly")
    p.add_argument("--vehicles", nargs="+", default=d.vehicles, metavar="NAME",
                   help="vehicles to learn from and publish to (default: '*', every one)")
    p.add_argument("--algo", default=d.algo, choices=ALGOS)
    p.add_argument("--reward", default=d.reward, choices=REWARDS,
                   help="goal reward that rewrites each episode (default: abr)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, actor.pt)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--updates-per-step", type=float, default=d.updates_per_step,
                   help="updates per new env step (default: 1)")
    p.add_argument("--warmup", type=int, default=d.warmup, metavar="TRANSITIONS",
                   help="transitions in the buffer before updates start (default: 1000)")
    p.add_argument("--critic-warmup", type=int, default=d.critic_warmup, metavar="UPDATES",
                   help="the first updates train the critic only, so a fresh critic does not "
                        "drag a trained --init-actor around (default: 1000)")
    p.add_argument("--publish-every", type=int, default=d.publish_every, metavar="EPISODES")
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                   metavar="EPISODES")
    p.add_argument("--init-actor", default=d.init_actor,
                   help="'shipped' (default), 'scratch' or an actor file")
    p.add_argument("--buffer-size", type=int, default=d.buffer_size)
    p.add_argument("--max-episodes", type=int, default=d.max_episodes,
                   help="stop after this many episodes (default 0: until Ctrl-C/SIGTERM)")
    p.add_argument("--grace", type=float, default=d.grace_s, metavar="S",
                   help="how long an ended episode waits for late messages (default: 2)")
    p.add_argument("--threads", type=int, default=d.threads, help="torch threads")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_bus_flags(p, vehicle=False)
    p.set_defaults(func=cmd_learner)
