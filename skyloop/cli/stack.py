"""The stack's subcommands: ``sim``, ``perception``, ``policy``, ``bridge`` and ``up``
(``record``, ``router`` and ``certs`` are in ``skyloop.cli.tools``). Each node is a thin
binding of a core to the bus (see the ``node.py`` of its package); this module only
parses flags, opens the Zenoh session (``SKYLOOP_ZENOH_*`` environment, overridden by
``--mode/--connect/--listen``), handles SIGINT/SIGTERM and closes things in order.

The options of ``sim``, ``perception``, ``policy``, ``bridge`` and ``up`` are generated
from their settings dataclasses (``skyloop.cli.stack_settings``) with tyro
(``skyloop.cli.dataclass_cli.parse``): :data:`COMMANDS`, :func:`parse_node`."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any

from skyloop.cli.dataclass_cli import parse
from skyloop.cli.stack_settings import (
    BridgeCommand,
    BusFlags,
    PerceptionCommand,
    PolicyCommand,
    SimCommand,
    UpCommand,
    bare_viz,
)


def _open_bus(args: BusFlags) -> Any:
    from bus.node import Bus
    from bus.session import SessionConfig

    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        stream=sys.stderr)
    return Bus.open(SessionConfig.from_flags(args.mode, args.connect, args.listen,
                                               args.zenoh_config))


def _stop_event() -> Any:
    """SIGINT and SIGTERM set the returned flag (``skyloop.signals.StopFlag``: no lock)."""
    from skyloop.signals import stop_flag_on_signals

    return stop_flag_on_signals()


def _raise_on_term() -> None:
    """SIGTERM interrupts the main thread as Ctrl-C does (``skyloop.signals``)."""
    from skyloop.signals import stop_on_sigterm

    stop_on_sigterm()


# ----------------------------------------------------------------------------- nodes
def cmd_sim(args: SimCommand) -> int:
    from sitl.node.node import SimNode, SimNodeConfig

    _raise_on_term()
    values = args.params
    bus = _open_bus(args)
    node = None
    try:
        node = SimNode(bus, SimNodeConfig(scenario=args.scenario, episodes=args.episodes,
                                          seed=args.seed, vehicle=args.vehicle,
                                          realtime=args.realtime, max_steps=args.max_steps,
                                          free_flight=args.free_flight, params=values,
                                          goals_from_bus=args.goals_from_bus,
                                          lockstep_timeout_s=args.lockstep_timeout))
        go = (lambda: sys.stdin.readline()) if args.wait_go else None
        node.run(lambda line: print(line, flush=True), go)
    finally:
        bus.close()
        if node is not None:
            from skyloop.launcher import counters_line

            # what the sim's bounded inboxes (commands, goals, parameters) dropped
            print(counters_line(node.counters()), flush=True)
    return 0


def cmd_perception(args: PerceptionCommand) -> int:
    from perception.node import PerceptionNode
    from perception.observation import ObservationConfig

    stop = _stop_event()
    bus = _open_bus(args)
    config = ObservationConfig() if args.encoding is None else \
        ObservationConfig(encoding=args.encoding)
    node = PerceptionNode(bus, args.vehicle, config)
    logging.getLogger("skyloop.perception").info("perception up for %s", args.vehicle)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        node.close()  # the worker first: it publishes on the bus
        bus.close()
        logging.getLogger("skyloop.perception").info(
            "published %d observations, dropped %d messages (overload; %d episode events "
            "or parameters among them)", node.published, node.dropped, node.dropped_events)
        from skyloop.launcher import counters_line

        print(counters_line({"published": node.published, "dropped": node.dropped,
                             "dropped_events": node.dropped_events}), flush=True)
    return 0


def policy_client_config(args: PolicyCommand) -> Any:
    """The policy's MAVLink endpoint from its flags; ValueError (naming the flag) if
    they ask for something unsafe, e.g. a non-loopback ``--api-host`` without
    ``--expose``."""
    from mavlink_bridge.offboard_client import OffboardClientConfig
    from mavlink_bridge.security import check_bind, security_from_args

    security = security_from_args(args)
    check_bind(args.api_host, security.expose, "the policy's MAVLink port (--api-host)")
    return OffboardClientConfig(listen_host=args.api_host, listen_port=args.api_port,
                                security=security)


def bridge_link_config(args: BridgeCommand) -> Any:
    """The vehicle's MAVLink links from the bridge's flags; ValueError (naming the flag)
    for a non-loopback ``--bind`` without ``--expose`` or an unreadable signing key."""
    from mavlink_bridge.security import check_bind, security_from_args
    from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig

    security = security_from_args(args)
    check_bind(args.bind, security.expose, "the vehicle's MAVLink links (--bind)")
    params_file = None if args.params_file == "none" else args.params_file
    return VehicleLinkConfig(
        api=LinkConfig(args.api_local_port, args.api_port, args.bind, args.api_host),
        gcs=None if args.no_gcs else LinkConfig(args.gcs_local_port, args.gcs_port,
                                                args.bind, args.gcs_host),
        params_file=params_file, security=security)


def _config_or_exit(build: Any, args: Any, name: str) -> Any:
    try:
        return build(args)
    except (ValueError, OSError) as err:
        raise SystemExit(f"skyloop {name}: {err}") from None


def cmd_policy(args: PolicyCommand) -> int:
    from policy.nodes.node import READY_LINE, PolicyNode

    if args.policy == "none":
        print("skyloop policy: --policy none: nothing to fly", file=sys.stderr)
        return 0
    client_config = _config_or_exit(policy_client_config, args, "policy")
    import torch

    from bus.task import TASK
    from policy.training.evaluate import stack_controller

    torch.set_num_threads(1)
    controller = stack_controller(args.actor)
    # Until it flies, SIGTERM interrupts whatever start-up waits on (the heartbeat, arming,
    # the takeoff), as Ctrl-C does (main exits 130 or 143, after the ``finally`` below has
    # closed what was opened); from then on the loop checks ``stop`` every step.
    from mavlink_bridge.offboard_client import OffboardError
    from mavlink_bridge.transport import LinkBindError

    _raise_on_term()
    bus = _open_bus(args)
    weights = node = None
    try:
        if args.weights_from_bus:
            from policy.nodes.weights import WeightsFollower

            weights = WeightsFollower(bus, args.vehicle, controller,
                                      emit=lambda line: print(line, flush=True))
        try:
            # the state it was trained on: its frames (the scripted controller: the task's)
            frames = getattr(controller, "trained_task", TASK).frames
            node = PolicyNode(bus, controller, args.vehicle, client_config, frames=frames,
                              lockstep=not args.realtime, weights=weights, hold=args.hold)
        except LinkBindError as err:
            raise ValueError(f"{err} (choose another with --api-port)") from None
        try:
            node.start(args.takeoff_altitude, timeout=args.startup_timeout)
        except OffboardError as err:  # denied or no vehicle until the timeout: one line
            print(f"skyloop policy: could not take the vehicle into OFFBOARD: {err}",
                  file=sys.stderr, flush=True)
            return 1
        stop = _stop_event()
        bus.declare_ready(args.vehicle, "policy")  # what the launcher waits on
        print(READY_LINE, flush=True)
        node.run(stop.is_set)
    finally:
        if weights is not None:
            logging.getLogger("skyloop.policy").info("weights: %s", weights.counters())
        bus.close()
        if node is not None:
            node.close()
            from skyloop.launcher import counters_line

            # what the launcher's summary (and `up --json`) shows of the policy: setpoints
            # sent, holds because the vehicle or perception is not as trained, bad
            # actions, what its bounded inboxes dropped
            print(counters_line(node.counters()), flush=True)
    return 0


def cmd_bridge(args: BridgeCommand) -> int:
    from mavlink_bridge.node import BridgeNode

    link = _config_or_exit(bridge_link_config, args, "bridge")
    overrides = args.params
    from mavlink_bridge.transport import LinkBindError

    stop = _stop_event()
    bus = _open_bus(args)
    try:
        node = BridgeNode(bus, args.vehicle, link, command_timeout_s=args.command_timeout,
                          param_overrides=overrides)
    except LinkBindError as err:
        bus.close()
        flag = {"api": "--api-local-port", "gcs": "--gcs-local-port"}.get(err.link, "")
        raise ValueError(f"{err} (choose another with {flag})" if flag else str(err)) from None
    logging.getLogger("skyloop.bridge").info(
        "bridge up: api %s -> %s:%d, gcs %s", node.link.address("api"), args.api_host,
        args.api_port, "off" if args.no_gcs else f"-> {args.gcs_host}:{args.gcs_port}")
    try:
        node.run(stop.is_set)
    finally:
        bus.close()
        node.close()
        logging.getLogger("skyloop.bridge").info("bridge: %s", node.counters())
        from skyloop.launcher import counters_line

        print(counters_line(node.counters()), flush=True)
    return 0


def cmd_up(args: UpCommand) -> int:
    from skyloop.launcher import run_up

    return run_up(args)


# ----------------------------------------------------------------------------- parsers
#: name -> (settings dataclass, what runs it, one line of help)
COMMANDS: dict[str, tuple[type, Callable[[Any], int], str]] = {
    "sim": (SimCommand, cmd_sim, "simulator node: the vehicle, its commander and failsafes, "
                                 "seeded episodes on the bus"),
    "perception": (PerceptionCommand, cmd_perception,
                   "perception node: scan + odom + goal -> observation"),
    "policy": (PolicyCommand, cmd_policy,
               "policy node: observation -> actor -> MAVLink setpoints"),
    "bridge": (BridgeCommand, cmd_bridge, "the vehicle's MAVLink endpoint (commands go to "
                                          "the sim's commander over the bus)"),
    "up": (UpCommand, cmd_up, "run the whole stack (sim, perception, policy, bridge, "
                              "[record], [router]) for N episodes"),
}


def parse_node(argv: Sequence[str]) -> Any:
    """The settings of ``skyloop NAME ARGS`` (``argv`` = [NAME, *ARGS], NAME one of
    :data:`COMMANDS`); ``--help`` exits 0, a bad command line exits 2 with one line."""
    name, rest = argv[0], list(argv[1:])
    cls, _, description = COMMANDS[name]
    if name == "up":
        rest = bare_viz(rest)
    return parse(cls, rest, prog=f"skyloop {name}", description=description)


def run_node(name: str, argv: Sequence[str]) -> int:
    """``skyloop NAME ARGS``: parse (exit 2 on a bad value, before anything starts), run."""
    settings = parse_node([name, *argv])
    return COMMANDS[name][1](settings)


def add_stack_commands(sub: Any) -> None:
    """Register the stack's subcommands on ``sub`` (argparse subparsers) for
    ``skyloop --help``; ``skyloop.cli.main.main`` hands each its own command line."""
    for name, (_, _, text) in COMMANDS.items():
        p = sub.add_parser(name, help=f"{text} (see '{name} --help')", add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(func=lambda args, name=name: run_node(name, args.rest))
