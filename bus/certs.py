"""A certificate authority, one certificate per node, and the Zenoh configuration files
that make the bus let no one in (:func:`make_certs`; the ``skyloop certs`` command,
``skyloop.tool_cli``).

The bus of a stack that leaves loopback (docker, several hosts) runs through a router
(``skyloop up --router``, ``docker/compose.yaml``) on a ``tls/`` endpoint with mutual
TLS: the router and every node present a certificate of this CA, and a session without
one, or with another CA's, cannot connect. On top, the router's access control
(Zenoh's ``access_control``, matching the certificates' common names) lets only the
bridge put the vehicle's inputs (``cmd_vel``, ``goal``, ``params``) and ask its
commander (``command``): any other node's attempt is dropped at the router. Everything
is standard Zenoh configuration (``transport/link/tls``, ``access_control``) in one
JSON5 file per node, given with ``--zenoh-config FILE`` or ``ZENOH_CONFIG``; skyloop's
flags still choose the mode and endpoints.

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

#: the nodes of a stack (and the router), one certificate each
NODES = ("router", "sim", "perception", "policy", "bridge", "record", "viz", "learner",
         "launcher")
#: only this node may put the vehicle's inputs and ask its commander
COMMANDER = "bridge"
#: what the access control reserves to :data:`COMMANDER`
VEHICLE_INPUTS = ("skyloop/*/cmd_vel", "skyloop/*/goal", "skyloop/*/params")
VEHICLE_COMMANDS = ("skyloop/*/command",)
#: how long the CA and the certificates are valid (days)
DAYS = 825


def _openssl(*args: str) -> None:
    if shutil.which("openssl") is None:
        raise FileNotFoundError("skyloop certs needs the openssl command (apt-get install "
                                "openssl)")
    subprocess.run(["openssl", *args], check=True, capture_output=True)


def access_control(nodes: Sequence[str]) -> dict:
    """The router's ``access_control``: every node but :data:`COMMANDER` is denied
    putting the vehicle's inputs and querying its commander."""
    others = [n for n in nodes if n != COMMANDER]
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [
            {"id": "vehicle inputs", "permission": "deny", "flows": ["ingress"],
             "messages": ["put", "delete"], "key_exprs": list(VEHICLE_INPUTS)},
            {"id": "vehicle commands", "permission": "deny", "flows": ["ingress"],
             "messages": ["query"], "key_exprs": list(VEHICLE_COMMANDS)},
        ],
        "subjects": [{"id": "not the bridge", "cert_common_names": others}],
        "policies": [{"rules": ["vehicle inputs", "vehicle commands"],
                      "subjects": ["not the bridge"]}],
    }


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

