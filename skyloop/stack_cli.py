"""The stack's subcommands: ``sim``, ``perception``, ``policy``, ``bridge``, ``record``,
``router`` and ``up``. Each node is a thin binding of a core to the bus (see the
``node.py`` of its package); this module only parses flags, opens the Zenoh session
(``SKYLOOP_ZENOH_*`` environment, overridden by ``--mode/--connect/--listen``), handles
SIGINT/SIGTERM and closes things in order."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from bus.task import TASK
from skyloop.argtypes import add_bus_flags, nonnegative_int, positive_float, positive_int

MAVLINK_DEFAULTS = {"api_port": 14540, "api_local_port": 14580, "gcs_port": 14550,
                    "gcs_local_port": 18570}


def _clock_args(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--lockstep", dest="realtime", action="store_false", default=False,
                   help="advance only when the step's command arrived (default)")
    g.add_argument("--realtime", dest="realtime", action="store_true",
                   help="pace by the wall clock at 10 Hz")


def _open_bus(args: argparse.Namespace) -> Any:
    from bus.node import Bus
    from bus.session import SessionConfig

    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        stream=sys.stderr)
    return Bus.open(SessionConfig.from_flags(args.mode, args.connect, args.listen,
                                               args.zenoh_config))


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _raise_on_term() -> None:
    """SIGTERM interrupts the main thread as Ctrl-C does (``skyloop.signals``)."""
    from skyloop.signals import stop_on_sigterm

    stop_on_sigterm()


# ----------------------------------------------------------------------------- nodes
def parse_params(items: list[str]) -> dict[str, float]:
    """``NAME=VALUE`` flags -> a checked parameter dict (``bus.params``); SystemExit
    naming the bad one."""
    from bus import params

    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError(f"{item!r} is not NAME=VALUE")
            out[name] = params.check(name, value)
        except ValueError as err:
            raise SystemExit(f"--param: {err}") from None
    return out


def cmd_sim(args: argparse.Namespace) -> int:
    from sitl.node import SimNode, SimNodeConfig

    _raise_on_term()
    values = parse_params(args.param)
    bus = _open_bus(args)
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
    return 0


def cmd_perception(args: argparse.Namespace) -> int:
    from perception.node import PerceptionNode

    stop = _stop_event()
    bus = _open_bus(args)
    node = PerceptionNode(bus, args.vehicle)
    logging.getLogger("skyloop.perception").info("perception up for %s", args.vehicle)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        node.close()  # the worker first: it publishes on the bus
        bus.close()
        logging.getLogger("skyloop.perception").info(
            "published %d observations, dropped %d messages (overload)", node.published,
            node.dropped)
    return 0


def policy_client_config(args: argparse.Namespace) -> Any:
    """The policy's MAVLink endpoint from its flags; ValueError (naming the flag) if
    they ask for something unsafe, e.g. a non-loopback ``--api-host`` without
    ``--expose``."""
    from mavlink_bridge.offboard_client import OffboardClientConfig
    from mavlink_bridge.security import check_bind, security_from_args

    security = security_from_args(args)
    check_bind(args.api_host, security.expose, "the policy's MAVLink port (--api-host)")
    return OffboardClientConfig(listen_host=args.api_host, listen_port=args.api_port,
                                security=security)


def bridge_link_config(args: argparse.Namespace) -> Any:
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


def _config_or_exit(build: Any, args: argparse.Namespace, name: str) -> Any:
    try:
        return build(args)
    except (ValueError, OSError) as err:
        raise SystemExit(f"skyloop {name}: {err}") from None


def cmd_policy(args: argparse.Namespace) -> int:
    from policy.node import READY_LINE, PolicyNode

    if args.policy == "none":
        print("skyloop policy: --policy none: nothing to fly", file=sys.stderr)
        return 0
    client_config = _config_or_exit(policy_client_config, args, "policy")
    import torch

    from policy.evaluate import make_controller

    torch.set_num_threads(1)
    controller = make_controller(None if args.policy == "shipped" else args.policy)
    # Until it flies, SIGTERM interrupts whatever start-up waits on (the heartbeat, arming,
    # the takeoff), as Ctrl-C does (main exits 130 or 143, after the ``finally`` below has
    # closed what was opened); from then on the loop checks ``stop`` every step.
    from mavlink_bridge.transport import LinkBindError

    _raise_on_term()
    bus = _open_bus(args)
    weights = node = None
    try:
        if args.weights_from_bus:
            from policy.weights import WeightsFollower

            weights = WeightsFollower(bus, args.vehicle, controller,
                                      emit=lambda line: print(line, flush=True))
        try:
            node = PolicyNode(bus, controller, args.vehicle, client_config,
                              lockstep=not args.realtime, weights=weights, hold=args.hold)
        except LinkBindError as err:
            raise ValueError(f"{err} (choose another with --api-port)") from None
        node.start(args.takeoff_altitude)
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
    return 0


def cmd_bridge(args: argparse.Namespace) -> int:
    from mavlink_bridge.node import BridgeNode

    link = _config_or_exit(bridge_link_config, args, "bridge")
    overrides = parse_params(args.param)
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
    return 0


def passthrough(name: str, argv: list[str]) -> int:
    """``record``, ``router`` and ``certs`` parse their own flags (``bus.record``,
    ``bus.session``, ``bus.certs``)."""
    if name == "record":
        from bus.record import main

        return main(argv)
    if name == "certs":
        from bus.certs import main as certs_main

        return certs_main(argv)
    from bus.session import router_main

    return router_main(argv)


def cmd_record(args: argparse.Namespace) -> int:
    return passthrough("record", args.rest)


def cmd_router(args: argparse.Namespace) -> int:
    return passthrough("router", args.rest)


def cmd_certs(args: argparse.Namespace) -> int:
    return passthrough("certs", args.rest)


def cmd_up(args: argparse.Namespace) -> int:
    from skyloop.launcher import run_up

    return run_up(args)


# ----------------------------------------------------------------------------- parsers
def add_stack_commands(sub: Any) -> None:
    """Register the stack's subcommands on ``sub`` (argparse subparsers)."""
    from mavlink_bridge.security import add_security_args

    p = sub.add_parser("sim", help="simulator node: the vehicle, its commander and "
                                   "failsafes, seeded episodes on the bus")
    add_bus_flags(p)
    _clock_args(p)
    p.add_argument("--scenario", default="valley")
    p.add_argument("--episodes", type=nonnegative_int, default=1,
                   help="episodes to run (--free-flight: goals to reach, 0: until stopped)")
    p.add_argument("--free-flight", action="store_true",
                   help="no seeded placements: wait on the ground for a ground station; "
                        "an episode is one goal, no timeout")
    p.add_argument("--goals-from-bus", action="store_true",
                   help="free flight toward goals on the goal topic only (a ground station's "
                        "missions and clicks); between goals the vehicle holds")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="vehicle parameter (bus/params.py: COM_OF_LOSS_T, SKY_HOLD_LAND_T, "
                        "MPC_XY_VEL_MAX, MPC_Z_VEL_MAX, MIS_TAKEOFF_ALT, GF_MAX_HOR_DIST, "
                        "SKY_FLIGHT_LVL, SKY_ICO_RADIUS)")
    p.add_argument("--lockstep-timeout", type=positive_float, default=2.0,
                   help="lockstep: wall seconds to wait for a step's command in OFFBOARD "
                        "before flying without it (default 2)")
    p.add_argument("--seed", type=int, default=0, help="episode i uses seed + i")
    p.add_argument("--max-steps", type=positive_int, default=TASK.max_steps,
                   help="timeout in control steps (default: %(default)s, bus.task)")
    p.add_argument("--wait-go", action="store_true",
                   help="after warming up, print SKYLOOP-SIM-READY and wait for a stdin line")
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("perception", help="perception node: scan + odom + goal -> observation")
    add_bus_flags(p)
    p.set_defaults(func=cmd_perception)

    p = sub.add_parser("policy", help="policy node: observation -> actor -> MAVLink setpoints")
    add_bus_flags(p)
    _clock_args(p)
    p.add_argument("--policy", default=None,
                   help="actor file, 'scripted', 'none' or 'shipped' (default)")
    p.add_argument("--api-host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--api-port", type=int, default=MAVLINK_DEFAULTS["api_port"],
                   help="UDP port to listen on (PX4 SITL API link: 14540)")
    p.add_argument("--takeoff-altitude", type=float, default=None)
    p.add_argument("--weights-from-bus", action="store_true",
                   help="load actor weights a learner publishes (topic 'actor'), swapped in "
                        "between episodes")
    add_security_args(p)
    p.add_argument("--hold", action="store_true",
                   help="between episodes stream a zero setpoint (hover in OFFBOARD) and take "
                        "OFFBOARD again at a new episode (goals from a ground station)")
    p.set_defaults(func=cmd_policy)

    p = sub.add_parser("bridge", help="the vehicle's MAVLink endpoint (commands go to "
                                      "the sim's commander over the bus)")
    add_bus_flags(p)
    p.add_argument("--bind", default="127.0.0.1", help="local address of both links")
    p.add_argument("--api-host", default="127.0.0.1", help="where the offboard client is")
    p.add_argument("--api-port", type=int, default=MAVLINK_DEFAULTS["api_port"])
    p.add_argument("--api-local-port", type=int, default=MAVLINK_DEFAULTS["api_local_port"])
    p.add_argument("--gcs-host", default="127.0.0.1", help="where the ground station is")
    p.add_argument("--gcs-port", type=int, default=MAVLINK_DEFAULTS["gcs_port"])
    p.add_argument("--gcs-local-port", type=int, default=MAVLINK_DEFAULTS["gcs_local_port"])
    p.add_argument("--no-gcs", action="store_true", help="no ground-station link")
    p.add_argument("--command-timeout", type=float, default=1.0,
                   help="seconds to wait for the sim's answer to a command (then "
                        "TEMPORARILY_REJECTED)")
    p.add_argument("--params-file", default="auto", metavar="PATH|auto|none",
                   help="where ground-station parameter changes persist (auto: "
                        "$XDG_STATE_HOME/skyloop/params-sys<id>.json; none: memory only)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="parameter value for this run (not persisted; wins over the file); "
                        "`skyloop up` passes the sim's --param here too")
    add_security_args(p)
    p.set_defaults(func=cmd_bridge)

    p = sub.add_parser("record", help="record skyloop/** into MCAP (see 'record --help')",
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("router", help="Python Zenoh router (see 'router --help')",
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("certs", help="a CA, node certificates and Zenoh configs for a bus "
                                     "with mutual TLS and access control (see 'certs --help')",
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_certs)

    from skyloop.launcher import add_up_parser

    add_up_parser(sub, cmd_up)
