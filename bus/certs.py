"""A certificate authority, one certificate per node, and the Zenoh configuration files
that make the bus let no one in (:func:`make_certs`; the ``skyloop certs`` command,
``skyloop.cli.tools``).

The bus of a stack that leaves loopback (docker, several hosts) runs through a router
(``skyloop up --router``, ``docker/compose.yaml``) on a ``tls/`` endpoint with mutual
TLS: the router and every node present a certificate of this CA, and a session without
one, or with another CA's, cannot connect. On top, the router's access control
(Zenoh's ``access_control``, :func:`access_control`) decides by the certificate's
common name, and denies by default: a message that no rule below allows is dropped at
the router. A session on another link (a ``tcp/`` endpoint added to the router)
matches no subject: nothing at all is allowed to it.

* Any session of this CA (``link_protocols: ["tls"]``, whatever its common name; e.g. a
  ground tool given a certificate later with ``skyloop certs --nodes gcs``) is a
  read-only tool: it may declare subscribers and liveliness subscribers and ask for
  liveliness tokens (``skyloop.health``), and the router delivers to it what it
  subscribed to. It may not put anything, declare a queryable, query, or hold a
  readiness token: fake telemetry or a fake ``ready`` would steer the stack as surely as
  a setpoint.
* The nodes named when the router's configuration was written (the ``nodes`` of
  :func:`make_certs`, the router excepted) may also put the telemetry topics, every
  topic of ``bus.keys.TOPICS`` but the vehicle's inputs and commands
  (:data:`TELEMETRY`, each ``skyloop/*/<topic>``), and hold readiness tokens
  (``skyloop/*/ready/*``).
* Only :data:`COMMANDER` (the bridge) may put the vehicle's inputs
  (:data:`VEHICLE_INPUTS`: ``cmd_vel``, ``goal``, ``params``) and query its commander
  (:data:`VEHICLE_COMMANDS`), and only :data:`VEHICLE` (the sim) may declare the
  commander's queryable and answer it. The policy commands the vehicle through the
  bridge (MAVLink OFFBOARD setpoints), not on the bus: no other node publishes these
  keys (``sitl/``, ``perception/``, ``policy/``, ``mavlink_bridge/``).

Every allowed key is a pattern of concrete topics, so a put on a wildcard key
(``skyloop/**``, which Zenoh delivers to every matching subscriber, the sim's
``cmd_vel`` among them) is allowed to no one. The common names are fixed when the
router's ``router.json5`` is written: certificates made later with the same CA are
read-only tools until that file is written again with their names.

The router counts what its access control refuses (``skyloop router``, ``bus.denials``).
Zenoh counts the messages it drops there only when built with its ``stats`` feature (the
admin space's ``@/<zid>/router/metrics``); the eclipse-zenoh wheel is not (1.10.2: that
key answers only ``zenoh_build_info``), and a refused put or query is dropped silently:
the sender gets no error, a query just times out. So ``skyloop router`` reads Zenoh's own
log of the decisions (the target ``zenoh::net::routing::interceptor::access_control`` at
TRACE, which it turns on itself, whatever ``RUST_LOG`` says besides: a line per message,
"Using cached result: <zid> is unauthorized to Put (ingress) on skyloop/uav1/cmd_vel")
and counts each refused message by kind and direction (``denied``,
``denied_put_ingress``, ...) in its counters line, which ``skyloop up --router`` puts in
its summary. The decisions are shown only when ``RUST_LOG`` asks for that target at
TRACE (``skyloop up -v`` shows the router's output). Not counted: a session that matches
no subject (one on a ``tcp/`` link), which Zenoh refuses without a line. The cost is the
log: about 8 us of the router's CPU per refused message and 9 us per allowed one
(``bus.denials``).

Everything is standard Zenoh configuration (``transport/link/tls``, ``access_control``)
in one JSON5 file per node, given with ``--zenoh-config FILE`` or ``ZENOH_CONFIG``;
skyloop's flags still choose the mode and endpoints.

The keys and certificates are made with the ``openssl`` command (P-256, SAN
``localhost`` and ``127.0.0.1`` plus ``--host`` names); the recipe, for doing it by
hand, is the ``openssl`` calls below.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

from bus import keys

#: the nodes of a stack (and the router), one certificate each
NODES = ("router", "sim", "perception", "policy", "bridge", "record", "viz", "learner",
         "launcher")
#: only this node may put the vehicle's inputs and query its commander
COMMANDER = "bridge"
#: only this node (the vehicle) may answer the commander's queries
VEHICLE = "sim"
_INPUT_TOPICS = (keys.CMD_VEL, keys.GOAL, keys.PARAMS)
_COMMAND_TOPICS = (keys.COMMAND,)


def _every_vehicle(topic: str) -> str:
    return keys.key("*", topic, wildcard=True)


#: what the access control reserves to :data:`COMMANDER` (puts, deletes)
VEHICLE_INPUTS = tuple(_every_vehicle(t) for t in _INPUT_TOPICS)
#: ... and (queries; the queryable and its replies: :data:`VEHICLE`)
VEHICLE_COMMANDS = tuple(_every_vehicle(t) for t in _COMMAND_TOPICS)
#: what every node of the stack may put: every other topic
TELEMETRY = tuple(_every_vehicle(t) for t in keys.TOPICS
                  if t not in _INPUT_TOPICS + _COMMAND_TOPICS)
#: the readiness tokens (``bus.keys.ready_key``) the nodes of the stack may hold
READY_TOKENS = (keys.ready_key("*"),)
#: how long the CA and the certificates are valid (days)
DAYS = 825


def _openssl(*args: str) -> None:
    if shutil.which("openssl") is None:
        raise FileNotFoundError("skyloop certs needs the openssl command (apt-get install "
                                "openssl)")
    subprocess.run(["openssl", *args], check=True, capture_output=True)


def access_control(nodes: Sequence[str]) -> dict:
    """The router's ``access_control`` (the module docstring): deny by default; read-only
    for any certificate of the CA; telemetry and readiness for ``nodes``; the vehicle's
    inputs and commands for :data:`COMMANDER`, the commander's queryable for
    :data:`VEHICLE` (those two only if among ``nodes``)."""
    ingress, egress = ["ingress"], ["egress"]
    rules = [
        {"id": "read", "permission": "allow", "flows": ingress,
         "messages": ["declare_subscriber", "declare_liveliness_subscriber",
                      "liveliness_query"], "key_exprs": ["**"]},
        # what the router sends a session: what it subscribed to or asked for, the
        # queries for a queryable it was allowed to declare, declarations
        {"id": "deliver", "permission": "allow", "flows": egress,
         "messages": ["put", "delete", "declare_subscriber", "query", "reply",
                      "declare_queryable", "liveliness_token", "declare_liveliness_subscriber",
                      "liveliness_query"], "key_exprs": ["**"]},
        {"id": "telemetry", "permission": "allow", "flows": ingress,
         "messages": ["put", "delete"], "key_exprs": list(TELEMETRY)},
        {"id": "readiness", "permission": "allow", "flows": ingress,
         "messages": ["liveliness_token"], "key_exprs": list(READY_TOKENS)},
        {"id": "vehicle inputs", "permission": "allow", "flows": ingress,
         "messages": ["put", "delete"], "key_exprs": list(VEHICLE_INPUTS)},
        {"id": "vehicle commands", "permission": "allow", "flows": ingress,
         "messages": ["query"], "key_exprs": list(VEHICLE_COMMANDS)},
        {"id": "commander", "permission": "allow", "flows": ingress,
         "messages": ["declare_queryable", "reply"], "key_exprs": list(VEHICLE_COMMANDS)},
    ]
    # a session of this CA: the router listens on tls/ with mutual TLS only
    subjects: list[dict] = [{"id": "certified", "link_protocols": ["tls"]}]
    policies: list[dict] = [{"rules": ["read", "deliver"], "subjects": ["certified"]}]
    stack = [n for n in dict.fromkeys(nodes) if n != "router"]
    for sid, names, granted in (
            ("stack", stack, ["telemetry", "readiness"]),
            ("the commander", [n for n in stack if n == COMMANDER],
             ["vehicle inputs", "vehicle commands"]),
            ("the vehicle", [n for n in stack if n == VEHICLE], ["commander"])):
        if names:  # Zenoh refuses an empty list
            subjects.append({"id": sid, "cert_common_names": names})
            policies.append({"rules": granted, "subjects": [sid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def zenoh_config(out: Path, node: str, nodes: Sequence[str]) -> dict:
    """One node's Zenoh configuration: mutual TLS with its certificate (the router's
    also carries the access control)."""
    side = "listen" if node == "router" else "connect"
    conf: dict = {"transport": {"link": {"tls": {
        "root_ca_certificate": str(out / "ca.pem"),
        f"{side}_private_key": str(out / f"{node}.key.pem"),
        f"{side}_certificate": str(out / f"{node}.pem"),
        "enable_mtls": True}}}}
    if node == "router":
        conf["access_control"] = access_control(nodes)
    return conf


def make_certs(out_dir: str | Path, nodes: Sequence[str] = NODES,
               hosts: Sequence[str] = (), days: int = DAYS) -> Path:
    """Write ``ca.pem`` (and its key), ``<node>.pem``/``<node>.key.pem`` and
    ``<node>.json5`` for each node into ``out_dir``; returns it."""
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    ca_key, ca = out / "ca.key.pem", out / "ca.pem"
    if not ca.exists():
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
                 "-nodes", "-keyout", str(ca_key), "-out", str(ca), "-days", str(days),
                 "-subj", "/CN=skyloop-ca")
    san = ",".join(["DNS:localhost", "IP:127.0.0.1", *(f"DNS:{h}" for h in hosts)])
    ext = out / "san.cnf"
    ext.write_text(f"subjectAltName={san}\n")
    for node in nodes:
        key, csr, cert = out / f"{node}.key.pem", out / f"{node}.csr", out / f"{node}.pem"
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                 "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={node}")
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key),
                 "-CAcreateserial", "-out", str(cert), "-days", str(days), "-extfile", str(ext))
        csr.unlink()
        key.chmod(0o600)
        (out / f"{node}.json5").write_text(json.dumps(zenoh_config(out, node, nodes),
                                                      indent=2) + "\n")
    ext.unlink()
    return out

