"""The settings of the stack's commands (``skyloop sim``, ``perception``, ``policy``,
``bridge`` and ``up``) as dataclasses; their command lines are generated from them with
tyro (``skyloop.cli.dataclass_cli.parse``), so each default lives once and ``--help`` shows
it with the choices, and a bad value is refused with one line naming the flag (exit 2)
before anything starts.

The flag groups several commands take are one mixin each, inherited, so their flags
stay flat (``--vehicle``, not ``--bus.vehicle``) and their attributes too
(``settings.vehicle``): ``VehicleFlag`` (``skyloop.cli.settings_base``, with the base and
the range checks), :class:`ZenohFlags` (the Zenoh session of a node:
``SessionConfig.from_flags``; with ``--vehicle``: :class:`BusFlags`), :class:`ClockFlags`
(``--lockstep``/``--realtime``), :class:`SecurityFlags`
(``mavlink_bridge.security.security_from_args`` reads them), :class:`MavlinkPorts`,
:class:`ScenarioFlag`, :class:`SimRules` (what ``up`` hands the sim) and
:class:`ViewFlags` (``skyloop view``/``viz``, in ``skyloop.cli.tools``).

Where a default belongs to a config of the code the flags feed, it is read from there:
the episode limits from the task specification (``bus.task.TASK``), the MAVLink ports
from ``mavlink_bridge.vehicle_link.VehicleLinkConfig`` and
``mavlink_bridge.offboard_client.OffboardClientConfig``. The sim's
(``sitl.node.step.SimNodeConfig``) are not imported here (seconds of imports before
``--help``); :class:`SimCommand` always passes its values on, and
tests/stack/test_cli_nodes.py checks both agree. Only light modules are imported here.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from bus.task import TASK
from mavlink_bridge.offboard_client import OffboardClientConfig
from mavlink_bridge.security import KEY_ENV
from mavlink_bridge.vehicle_link import VehicleLinkConfig
from policy.shipped import policy_path
from policy.training.settings import ConfigError
from skyloop.cli.settings_base import (
    Repeated,
    Settings,
    VehicleFlag,
    at_least,
    bare_flag,
    minutes_or_off,
    port,
    positive,
)
from skyloop.placement import PinMode

__all__ = ["DEMO_SEED", "BridgeCommand", "BusFlags", "ClockFlags", "MavlinkPorts",
           "PerceptionCommand", "PolicyCommand", "ScenarioFlag", "SecurityFlags", "Settings",
           "SimCommand", "SimRules", "UpCommand", "VehicleFlag", "ViewFlags", "ZenohFlags",
           "at_least", "bare_viz", "parse_params", "viz_target"]

_LINKS = VehicleLinkConfig()
assert _LINKS.api is not None and _LINKS.gcs is not None


# ----------------------------------------------------------------------------- checks
def parse_params(items: tuple[str, ...] | list[str]) -> dict[str, float]:
    """``NAME=VALUE`` flags -> a checked parameter dict (``bus.params``); ConfigError
    naming ``--param`` and the bad one."""
    from bus import params

    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError(f"{item!r} is not NAME=VALUE")
            out[name] = params.check(name, value)
        except ValueError as err:
            raise ConfigError("param", str(err)) from None
    return out


# ----------------------------------------------------------------------------- groups
DEMO_SEED = 1000  # the seeds `skyloop up` and `skyloop demo` fly (episode i: seed + i)


class ParamValues:
    """``params``: a command's repeatable ``--param NAME=VALUE`` (its ``param`` field) as a
    checked dict."""

    @property
    def params(self) -> dict[str, float]:
        return parse_params(self.param)  # type: ignore[attr-defined]


@dataclass(kw_only=True)
class ScenarioFlag(Settings):
    scenario: str = "valley"
    """a world, family:NAME or mix:A=w,B=w (sitl.world.scenario, sitl.world.families)"""


@dataclass(kw_only=True)
class ViewFlags(Settings):
    """Where a 3D view (Rerun) goes and what it draws (``skyloop.viewer``)."""

    viz: Annotated[str, tyro.conf.arg(metavar="TARGET")] = "spawn"
    """spawn (the native viewer), web (a web viewer on localhost) or save:PATH.rrd"""
    scan_every: Annotated[int, tyro.conf.arg(metavar="N")] = 5
    """draw the LiDAR scan every N steps"""
    web_port: int = 9090
    """--viz web: the viewer's HTTP port"""
    grpc_port: int = 9876
    """--viz web: the data's gRPC port"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "scan_every", 1)
        port(self, "web_port")
        port(self, "grpc_port")
        self.target  # noqa: B018 - a ConfigError naming --viz for a bad one

    @property
    def target(self) -> Any:
        """``--viz`` as a ``skyloop.viewer.Target``."""
        return viz_target(self.viz)


def viz_target(text: str) -> Any:
    """A ``--viz`` value as a ``skyloop.viewer.Target``; ConfigError naming ``--viz``."""
    from skyloop.viewer import parse_target

    try:
        return parse_target(text)
    except ValueError as err:
        problem = str(err).split(": ", 1)[-1]
        raise ConfigError("viz", f"{problem}, got {text!r}") from None


@dataclass(kw_only=True)
class ZenohFlags(Settings):
    """The Zenoh session of a node (``bus.session.SessionConfig.from_flags``: a flag
    given wins over the ``SKYLOOP_ZENOH_*`` environment) and its logging."""

    mode: Annotated[Literal["peer", "client"] | None, tyro.conf.arg(
        metavar="{peer,client}", help_behavior_hint="(default: $SKYLOOP_ZENOH_MODE or peer)",
    )] = None
    """Zenoh mode"""
    connect: Annotated[str | None, tyro.conf.arg(
        metavar="ENDPOINTS", help_behavior_hint="(default: $SKYLOOP_ZENOH_CONNECT)")] = None
    """Zenoh endpoints to connect to, comma-separated"""
    listen: Annotated[str | None, tyro.conf.arg(
        metavar="ENDPOINTS", help_behavior_hint="(default: $SKYLOOP_ZENOH_LISTEN)")] = None
    """Zenoh endpoints to listen on, comma-separated"""
    zenoh_config: Annotated[str | None, tyro.conf.arg(
        metavar="FILE", help_behavior_hint="(default: $ZENOH_CONFIG)")] = None
    """a Zenoh configuration file: TLS certificates, access control (skyloop certs)"""
    verbose: Annotated[bool, tyro.conf.arg(aliases=("-v",))] = False
    """debug logging"""


@dataclass(kw_only=True)
class BusFlags(ZenohFlags, VehicleFlag):
    """A node of one vehicle: ``--vehicle`` and the Zenoh flags."""


@dataclass(kw_only=True)
class ClockFlags(Settings):
    """Lockstep (the default) or real time; one of the two flags at most."""

    lockstep: Annotated[bool, tyro.conf.arg(help_behavior_hint="(the default)")] = False
    """advance only when the step's command arrived"""
    realtime: bool = False
    """pace by the wall clock at 10 Hz"""

    def validate(self) -> None:
        super().validate()
        if self.lockstep and self.realtime:
            raise ConfigError("realtime", "not allowed with argument --lockstep")


@dataclass(kw_only=True)
class SecurityFlags(Settings):
    """MAVLink security (``mavlink_bridge.security.security_from_args``)."""

    signing_key_file: Annotated[Path | None, tyro.conf.arg(metavar="PATH", help=(
        "MAVLink 2 signing key: 64 hex digits or a passphrase (SHA-256, as MAVProxy) or "
        "32 raw bytes"), help_behavior_hint=f"(default: ${KEY_ENV}, else no signing)")] = None
    allow_sysid: Annotated[tuple[int, ...], Repeated, tyro.conf.arg(metavar="N")] = ()
    """only this system id may send commands and setpoints"""
    expose: bool = False
    """allow binding MAVLink beyond 127.0.0.1 (e.g. --bind 0.0.0.0)"""

    def validate(self) -> None:
        super().validate()
        for sysid in self.allow_sysid:
            if not 1 <= sysid <= 255:
                raise ConfigError("allow_sysid", f"must be a system id (1..255), got {sysid}")


@dataclass(kw_only=True)
class ApiPort(Settings):
    api_port: int = OffboardClientConfig.listen_port
    """UDP port of the offboard client's link (PX4 SITL's API link)"""

    def validate(self) -> None:
        super().validate()
        port(self, "api_port")


@dataclass(kw_only=True)
class MavlinkPorts(ApiPort):
    """The vehicle's two MAVLink links, as PX4 SITL has them
    (``mavlink_bridge.vehicle_link.VehicleLinkConfig``)."""

    api_local_port: int = _LINKS.api.local_port
    """the vehicle's own UDP port of the API link"""
    gcs_port: int = _LINKS.gcs.remote_port
    """UDP port of the ground station (QGroundControl, MAVProxy)"""
    gcs_local_port: int = _LINKS.gcs.local_port
    """the vehicle's own UDP port of the ground-station link"""

    def validate(self) -> None:
        super().validate()
        for name in ("api_local_port", "gcs_port", "gcs_local_port"):
            port(self, name, least=0 if name.endswith("local_port") else 1)


@dataclass(kw_only=True)
class SimRules(ParamValues, ScenarioFlag):
    """What the sim flies: the scenario, the episode limit, the lockstep wait and the
    vehicle's parameters."""

    max_steps: int = TASK.max_steps
    """episode timeout in control steps (the task specification's, bus.task)"""
    lockstep_timeout: Annotated[float, tyro.conf.arg(metavar="S", help=(
        "lockstep: wall seconds the sim waits for a step's command in OFFBOARD before it "
        "steps without it and aborts the episode"))] = 2.0
    param: Annotated[tuple[str, ...], Repeated, tyro.conf.arg(metavar="NAME=VALUE", help=(
        "vehicle parameter (bus/params.py: COM_OF_LOSS_T, SKY_HOLD_LAND_T, MPC_XY_VEL_MAX, "
        "MPC_Z_VEL_MAX, MIS_TAKEOFF_ALT, GF_MAX_HOR_DIST, SKY_FLIGHT_LVL, "
        "SKY_ICO_RADIUS)"))] = ()

    def validate(self) -> None:
        super().validate()
        at_least(self, "max_steps", 1)
        positive(self, "lockstep_timeout")
        parse_params(self.param)


@dataclass(kw_only=True)
class PolicyFlag(Settings):
    policy: Annotated[str, tyro.conf.arg(
        metavar="FILE|scripted|none|shipped[:NAME]")] = "shipped"
    """an actor file, the scripted controller, no policy, or an actor skyloop ships
    (shipped: the default; shipped:NAME one by name, policy/shipped/__init__.py)"""

    def validate(self) -> None:
        super().validate()
        policy_path(self.policy)  # an unknown shipped:NAME, before any node starts

    @property
    def actor(self) -> str | None:
        """What ``policy.training.evaluate.make_controller`` takes: None for the shipped actor."""
        return None if self.policy == "shipped" else self.policy


# ----------------------------------------------------------------------------- commands
@dataclass(kw_only=True)
class SimCommand(SimRules, ClockFlags, BusFlags):
    """``skyloop sim``: the simulator node (``sitl.node.node.SimNode``). Its defaults repeat
    ``sitl.node.step.SimNodeConfig``'s (episodes, seed, lockstep timeout...) on purpose:
    importing the simulator costs every command line ~1 s (JSBSim, Embree), and this
    module is read for each one; tests/stack/test_cli_nodes.py
    (``test_defaults_agree_with_the_configs_they_feed``) fails when they part."""

    episodes: Annotated[int, tyro.conf.arg(metavar="N")] = 1
    """episodes to run (--free-flight: goals to reach, 0: until stopped)"""
    seed: int = 0
    """episode i uses seed + i"""
    free_flight: Annotated[bool, tyro.conf.arg(help=(
        "no seeded placements: wait on the ground for a ground station; an episode is one "
        "goal, no timeout"))] = False
    goals_from_bus: Annotated[bool, tyro.conf.arg(help=(
        "free flight toward goals on the goal topic only (a ground station's missions and "
        "clicks); between goals the vehicle holds"))] = False
    wait_go: bool = False
    """after warming up, print SKYLOOP-SIM-READY and wait for a stdin line"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "episodes", 0)


@dataclass(kw_only=True)
class EncodingFlag:
    """How perception computes the face values (``perception.faces``)."""

    encoding: Literal["distance", "proximity"] | None = None
    """perception's face values: distance from the face centre (eq. 3.2) or proximity 1 -
    |p| / p_radius; the policy flies only an actor trained with the same (skyloop train
    --encoding). Default: skyloop up, the actor's; skyloop perception, distance"""


@dataclass(kw_only=True)
class PerceptionCommand(EncodingFlag, BusFlags):
    """``skyloop perception``: scan + odometry + goal -> observation."""


@dataclass(kw_only=True)
class PolicyCommand(PolicyFlag, SecurityFlags, ApiPort, ClockFlags, BusFlags):
    """``skyloop policy``: observation -> actor -> MAVLink setpoints (an offboard client)."""

    api_host: str = OffboardClientConfig.listen_host
    """address to listen on for the vehicle's API link"""
    takeoff_altitude: Annotated[float | None, tyro.conf.arg(
        metavar="M", help_behavior_hint="(default: the vehicle's MIS_TAKEOFF_ALT)")] = None
    """takeoff altitude in metres"""
    weights_from_bus: bool = False
    """load actor weights a learner publishes (topic 'actor') between episodes"""
    hold: Annotated[bool, tyro.conf.arg(help=(
        "between episodes stream a zero setpoint (hover in OFFBOARD) and take OFFBOARD "
        "again at a new episode (goals from a ground station)"))] = False
    startup_timeout: Annotated[float, tyro.conf.arg(metavar="S")] = 30.0
    """seconds to wait for the vehicle's heartbeat, and then to have it armed and in
    OFFBOARD (denials are tried again meanwhile), before exiting with code 1"""

    def validate(self) -> None:
        super().validate()
        if self.takeoff_altitude is not None:
            positive(self, "takeoff_altitude")
        positive(self, "startup_timeout")


@dataclass(kw_only=True)
class BridgeCommand(ParamValues, SecurityFlags, MavlinkPorts, BusFlags):
    """``skyloop bridge``: the vehicle's MAVLink endpoint; commands go to the sim's
    commander over the bus."""

    bind: str = _LINKS.api.local_host
    """local address of both links"""
    api_host: str = _LINKS.api.remote_host
    """where the offboard client is"""
    gcs_host: str = _LINKS.gcs.remote_host
    """where the ground station is"""
    no_gcs: bool = False
    """no ground-station link"""
    command_timeout: Annotated[float, tyro.conf.arg(metavar="S")] = 1.0
    """seconds to wait for the sim's answer to a command (then TEMPORARILY_REJECTED)"""
    params_file: Annotated[str, tyro.conf.arg(metavar="PATH|auto|none", help=(
        "where ground-station parameter changes persist (auto: "
        "$XDG_STATE_HOME/skyloop/params-sys<id>.json; none: memory only)"))] = "auto"
    param: Annotated[tuple[str, ...], Repeated, tyro.conf.arg(metavar="NAME=VALUE", help=(
        "parameter value for this run (not persisted; wins over the file); `skyloop up` "
        "passes the sim's --param here too"))] = ()

    def validate(self) -> None:
        super().validate()
        positive(self, "command_timeout")
        parse_params(self.param)


@dataclass(kw_only=True)
class UpCommand(EncodingFlag, SimRules, MavlinkPorts, SecurityFlags, PolicyFlag, ClockFlags,
                VehicleFlag):
    """``skyloop up``: the whole stack as child programs (``skyloop.launcher``)."""

    episodes: Annotated[int | None, tyro.conf.arg(metavar="N", help_behavior_hint=(
        "(default: 5; --policy none / --goals gcs: until stopped)"))] = None
    """episodes (--policy none / --goals gcs: goals to reach)"""
    seed: int = DEMO_SEED
    """episode i uses seed + i"""
    goals: Annotated[Literal["seeded", "gcs"], tyro.conf.arg(help=(
        "seeded: episodes from --seed; gcs: the policy flies toward goals from a ground "
        "station (missions, reposition) and hovers in between, until stopped"))] = "seeded"
    router: bool = False
    """start a Python Zenoh router; every node in client mode"""
    zenoh_config_dir: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help=(
        "with --router: mutual TLS and access control on the bus, each node with "
        "DIR/<node>.json5 (what `skyloop certs --out DIR` writes)"))] = None
    hub: Annotated[str | None, tyro.conf.arg(
        metavar="ENDPOINT", help_behavior_hint="(default: a free loopback port)")] = None
    """Zenoh endpoint of the hub/router"""
    log_dir: Annotated[Path | None, tyro.conf.arg(metavar="DIR")] = None
    """record the run (MCAP) under this directory"""
    log_split_episodes: Annotated[int, tyro.conf.arg(metavar="N")] = 0
    """with --log-dir: a new MCAP file every N episodes (0: one file)"""
    log_split_minutes: Annotated[float, tyro.conf.arg(metavar="M")] = 0.0
    """with --log-dir: a new MCAP file at the first episode end after M minutes in the
    current one (0: off; `skyloop record --split-minutes`)"""
    log_compression: Literal["zstd", "lz4", "none"] = "zstd"
    """with --log-dir: MCAP chunk compression (zstd: about 40% smaller than none)"""
    json: Annotated[Path | None, tyro.conf.arg(metavar="PATH")] = None
    """write the summary here"""
    restart: Annotated[Literal["no", "on-failure"], tyro.conf.arg(help=(
        "on-failure: start a perception, bridge, policy or router that exits with a "
        "failure again, the run goes on (no: the run stops)"))] = "no"
    max_restarts: Annotated[int, tyro.conf.arg(metavar="N")] = 3
    """restarts per node with --restart on-failure"""
    viz: Annotated[str | None, tyro.conf.arg(metavar="[TARGET]", help=(
        "watch the run in 3D (Rerun): spawn (the native viewer; a bare --viz), web (a web "
        "viewer on localhost, for a headless machine; it stays up after the run until "
        "Ctrl-C) or save:PATH.rrd"), help_behavior_hint="(default: no viewer)")] = None
    viz_scan_every: Annotated[int, tyro.conf.arg(metavar="N")] = ViewFlags.scan_every
    """with --viz: draw the LiDAR scan every N steps"""
    pin: Annotated[PinMode, tyro.conf.arg(help=(
        "chain: the lockstep chain (sim, perception, policy, bridge, router) shares one "
        "core, the recorder and viewer run anywhere (skyloop.placement); auto: chain in "
        "lockstep without --log-dir or --viz, else off; off: the scheduler places every "
        "process"))] = "auto"
    verbose: Annotated[bool, tyro.conf.arg(aliases=("-v",))] = False
    """echo every node's output"""

    @property
    def ground_station(self) -> bool:
        """Free flight for a ground station (``--policy none`` or ``--goals gcs``)."""
        return self.policy == "none" or self.goals == "gcs"

    def resolved(self) -> UpCommand:
        """A copy with what these settings imply: a ground station's free flight runs in
        real time, until stopped unless ``--episodes`` says; else 5 episodes. (Not checked
        again: ``--episodes`` 0 here means until stopped.)"""
        out = copy.copy(self)
        if out.episodes is None:
            out.episodes = 0 if self.ground_station else 5
        if self.ground_station:
            out.realtime, out.lockstep = True, False
        return out

    def validate(self) -> None:
        super().validate()
        at_least(self, "episodes", 1)
        if self.zenoh_config_dir is not None and not self.router:
            raise ConfigError("zenoh_config_dir", "needs --router (mutual TLS through the "
                                                  "router)")
        at_least(self, "log_split_episodes", 0)
        minutes_or_off(self, "log_split_minutes")
        at_least(self, "max_restarts", 1)
        at_least(self, "viz_scan_every", 1)
        if self.viz is not None:
            viz_target(self.viz)


def bare_viz(argv: list[str]) -> list[str]:
    """``--viz`` given without a value (last, or before another flag) means
    ``--viz spawn``, as the argparse option with an optional value did."""
    return bare_flag(argv, "--viz", "spawn")
