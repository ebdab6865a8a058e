"""``skyloop up``: the whole process graph as child programs, one summary at the end.

Children are new programs (``python -m skyloop <node>``, never a fork of a process with
a Zenoh session), in their own session so a terminal Ctrl-C reaches only the launcher,
and with a parent-death signal so none outlives it. Default wiring: loopback peers
joined through a hub endpoint on a free port (``SKYLOOP_ZENOH_HUB``, so two stacks on
one machine do not meet); ``--router`` starts ``skyloop router`` and puts every node in
client mode.

Start: [router, until it listens], then every node at once; the sim warms up and flies its
ground phase (the vehicle on the ground, its commander answering requests) until "go" on its
stdin, which it gets once every node is ready, the policy in OFFBOARD (arm, takeoff
and offboard done the MAVSDK way, through the bridge to the sim's commander); then it runs
the episodes. Readiness comes over the bus, not stdout: every node declares the Zenoh
liveliness token ``skyloop/<vehicle>/ready/<node>`` when ready
(``bus.node.Bus.declare_ready``: perception subscribed and publishing, the bridge's
MAVLink sockets bound and its bus side up, the recorder and viewer subscribed, the sim
warmed up in its ground phase, the policy in OFFBOARD), and the launcher's own session
watches them; "go" waits for every one of :func:`ready_waits` (the router, started
first, is waited for until its endpoint accepts connections). In lockstep
every episode is the same as in the in-process env. ``--policy none``: no policy process;
the sim runs free flight in real time (the vehicle waits on the ground, disarmed, for a
ground station; an episode is one goal), until stopped or ``--episodes`` goals (default:
until stopped). ``--goals gcs``: the policy takes off and flies OFFBOARD as usual, but the
sim runs free flight in real time with goals from the bus only (``sim --goals-from-bus``): a
ground station's mission or reposition gives them (``mavlink_bridge.gcs.goals``), and between
goals the policy hovers (``policy --hold``); until stopped by default. ``--param
NAME=VALUE`` goes to the sim (``bus/params.py``). The stack makes the state the actor was
trained on (:func:`as_trained`: its recorded icosahedron radius as ``SKY_ICO_RADIUS``, which
perception's faces and the sim's LiDAR range follow, its encoding; the policy node stacks its
frames), unless ``--param SKY_ICO_RADIUS`` or ``--encoding`` says otherwise (a radius a
ground station saved in the parameter file gives way to the actor's). When the sim
finishes, the others get SIGTERM (the recorder closes its MCAP), then SIGKILL after the
grace period (a node that needed it is named: "force-killed NAME"; none should). If any child
dies first, or on Ctrl-C, every child is stopped within 5 s and the launcher exits non-zero,
naming the node that died and its last log line. With ``--restart on-failure`` a
perception, bridge, policy or ``--router`` router that exits with a failure is started
again (at most ``--max-restarts`` times each, named with its last log line each time),
with the policy when another is restarted (:data:`RESTARTABLE`; Zenoh clients reconnect
to a restarted router by themselves, in about 2.5 s), and the run goes on:
the vehicle's failsafe holds meanwhile, the episode in progress ends ``aborted``
(``sitl.node.node``) and the next one starts once the restarted policy is in OFFBOARD; the
summary counts the restarts. The sim and the recorder are never restarted (a new sim
would be a new run; a new recorder a second log).

Where the processes run: ``--pin`` (``skyloop.placement``; default ``auto``): in lockstep
without a recorder or viewer the chain a step passes through (sim, perception, policy,
bridge, router) shares one core (set in each child before it runs anything); ``chain``
pins it whatever runs beside it. The summary's ``cpus`` says what the kernel holds for
each node at "go".

Where the time goes: at "go" and again at the end of the episodes (as the sim's summary
line comes, before any node shuts down; failing that, once the sim has exited, before it
is reaped and before the others are stopped) the launcher reads each child's CPU time
(user + system, every thread, from ``/proc/<pid>/stat``; nothing where there is no
``/proc``), and the summary gives ``cpu_ms_per_step``: per node, the CPU milliseconds it
spent between the two (start-up, warm-up and shutdown excluded) per control step of the
episodes. A restarted node counts from its restart (its start-up included), without the
processes it replaced."""

from __future__ import annotations

import collections
import copy
import functools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bus.node import Bus
from bus.session import SessionConfig
from bus.task import TASK
from skyloop.cli.stack_settings import UpCommand, parse_params
from skyloop.placement import Placement, plan
from skyloop.signals import Stopped, block_until_started, stop_on_sigterm

# The lines the nodes print (sitl.node.node / policy.nodes.node; not imported: --help stays light);
# the READY lines are for people reading the output: readiness comes over the bus.
EPISODE_LINE = "SKYLOOP-EPISODE "
SUMMARY_LINE = "SKYLOOP-SUMMARY "
#: a node's last line: what it did and dropped (``counters_line``); the launcher sums them
#: per node over restarts into the summary's ``counters`` (the bounded queues' drops)
COUNTERS_LINE = "SKYLOOP-COUNTERS "
READY_LINE = "SKYLOOP-POLICY-READY"
SIM_READY_LINE = "SKYLOOP-SIM-READY"
#: the nodes that hold a readiness token (``skyloop/<vehicle>/ready/<node>``), in the
#: order the launcher waits for them, and how long it waits for each (s)
READY_NODES = ("sim", "policy", "perception", "bridge", "record", "viz")
READY_TIMEOUT_S = {"sim": 120.0, "policy": 120.0, "perception": 60.0, "bridge": 60.0,
                   "record": 60.0, "viz": 60.0}
STARTED_LINE = "started {name} (pid {pid})"  # one a child, and again on each restart
GRACE_S = 3.0
#: the nodes ``--restart on-failure`` starts again, and the nodes each one's restart
#: takes along (rest-for-one, as in a supervision tree: the policy flies on
#: perception's observations through the bridge's link, and joins the vehicle anew)
RESTARTABLE = {"perception": ("policy",), "bridge": ("policy",), "policy": (),
               "router": ("policy",)}


def started(line: str) -> tuple[str, int] | None:
    """(node, pid) of a :data:`STARTED_LINE` of ``skyloop up``'s output, else None
    (for tools and tests that watch a run: the newest pid of each node)."""
    words = line.split()
    if len(words) == 4 and words[0] == "started" and words[2] == "(pid" \
            and words[3].endswith(")") and words[3][:-1].isdigit():
        return words[1], int(words[3][:-1])
    return None


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` (all its threads) from
    ``/proc/<pid>/stat``; None where there is no ``/proc`` or the process is gone
    (an exited child still shows its time until it is reaped)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()  # the name may hold spaces
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
    except (OSError, ValueError, IndexError):
        return None


def exited(proc: subprocess.Popen) -> bool:
    """Whether ``proc`` has exited, without reaping it where the OS allows (its
    ``/proc`` entry, CPU time included, stays until :meth:`~subprocess.Popen.poll`)."""
    if proc.returncode is not None:
        return True
    try:
        return os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
    except (AttributeError, ChildProcessError, OSError):  # no waitid, or reaped already
        return proc.poll() is not None


def _preexec(launcher_pid: int, cpus: frozenset[int] | None) -> None:
    """In the child between fork and exec (no Zenoh, no thread yet: the threads it starts
    inherit them): its CPUs (``skyloop.placement``), then :func:`_pdeathsig`."""
    if cpus is not None:
        os.sched_setaffinity(0, cpus)
    _pdeathsig(launcher_pid)


def _pdeathsig(launcher_pid: int) -> None:  # in the child between fork and exec: no Zenoh
    """SIGTERM when the launcher (``launcher_pid``, taken before the fork) dies. The
    parent-death signal is armed only from the ``prctl`` on: a launcher that died since
    the fork sends none, so a child whose parent is no longer the launcher (reparented to
    init or a subreaper) exits at once, as the signal would have ended it (128 + SIGTERM),
    before it runs anything."""
    block_until_started()  # a stop signal in the interpreter's start-up waits for skyloop
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - not Linux: children may outlive a killed launcher
        pass
    if os.getppid() != launcher_pid:  # the launcher died between the fork and the prctl
        os._exit(128 + signal.SIGTERM)


@dataclass
class Child:
    """One child program and what it printed."""

    name: str
    proc: subprocess.Popen
    lines: collections.deque = field(default_factory=lambda: collections.deque(maxlen=50))
    reader: threading.Thread | None = None  # routes its output; done at end of output

    @property
    def last_line(self) -> str:
        for line in reversed(self.lines):
            if line.strip():
                return line.strip()
        return "(no output)"


class Graph:
    """The running children; reader threads route their output."""

    def __init__(self, env: dict[str, str], verbose: bool = False,
                 placement: Placement | None = None) -> None:
        self.env, self.verbose, self.placement = env, verbose, placement
        self.children: list[Child] = []
        self.episodes: list[dict] = []
        self.summary: dict | None = None
        self.log_path: str | None = None
        self.counters: dict[str, collections.Counter[str]] = {}  # node -> its last line's
        #: node -> set while its readiness token is on the bus (:meth:`on_ready`)
        self.ready = {name: threading.Event() for name in READY_NODES}
        self.restarts: collections.Counter[str] = collections.Counter()
        self.cpu_at_go: dict[int, float] = {}  # pid -> CPU seconds when "go" was sent
        self.cpu_at_end: dict[int, float] | None = None  # ... as the sim's summary came
        self.cpu_s: dict[str, float] = {}  # node -> CPU seconds from "go" to the end
        self.cpus: dict[str, list[int]] = {}  # node -> the CPUs it may use, at "go"
        self.zenoh_configs: Path | None = None  # ``skyloop certs`` output: <node>.json5
        self._lock = threading.Lock()

    def start(self, name: str, args: list[str], stdin: int | None = None) -> Child:
        env = self.env
        if self.zenoh_configs is not None:  # each node presents its own certificate
            env = dict(env, ZENOH_CONFIG=str(self.zenoh_configs / f"{name}.json5"))
        cpus = self.placement.cpus(name) if self.placement is not None else None
        proc = subprocess.Popen(
            [sys.executable, "-m", "skyloop", *args], env=env, stdin=stdin,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, bufsize=1, start_new_session=True,
            preexec_fn=functools.partial(_preexec, os.getpid(), cpus))
        child = Child(name, proc)
        self.children.append(child)
        child.reader = threading.Thread(target=self._read, args=(child,), daemon=True)
        child.reader.start()
        print(STARTED_LINE.format(name=name, pid=proc.pid), flush=True)
        return child

    def restart(self, child: Child, args: list[str]) -> Child:
        """Start ``child``'s program again in its place (stopped first if it runs)."""
        if child.proc.poll() is None:
            self._stop([child], GRACE_S)
        self.children.remove(child)
        self.restarts[child.name] += 1
        return self.start(child.name, args)

    def child(self, name: str) -> Child | None:
        return next((c for c in self.children if c.name == name), None)

    def _read(self, child: Child) -> None:
        assert child.proc.stdout is not None
        for raw in child.proc.stdout:
            line = raw.rstrip("\n")
            child.lines.append(line)
            if self.verbose:
                print(f"[{child.name}] {line}", file=sys.stderr, flush=True)
            if line.startswith(EPISODE_LINE):
                r = json.loads(line[len(EPISODE_LINE):])
                with self._lock:
                    self.episodes.append(r)
                print(f"episode {r['episode']} (seed {r['seed']}): {r['outcome']} in "
                      f"{r['steps']} steps, path {r['path_length']:.1f} m", flush=True)
            elif line.startswith(SUMMARY_LINE):
                if child.name == "sim" and self.cpu_at_go:  # the episodes are over
                    self.cpu_at_end = self.read_cpu()
                self.summary = json.loads(line[len(SUMMARY_LINE):])
            elif line.startswith(COUNTERS_LINE):
                said = json.loads(line[len(COUNTERS_LINE):])
                with self._lock:
                    self.counters.setdefault(child.name, collections.Counter()).update(said)
            elif child.name == "record" and line.startswith("recorded "):
                self.log_path = line.rsplit(" into ", 1)[-1].split(";")[0]
            elif child.name == "viz" and line.startswith("viz: drawing"):
                print(line, flush=True)  # where to look (the web viewer's address)

    def read_cpu(self) -> dict[int, float]:
        """CPU seconds of every child (pid -> s) that ``/proc`` still shows."""
        return {c.proc.pid: t for c in list(self.children)
                if (t := cpu_seconds(c.proc.pid)) is not None}

    def affinity(self) -> dict[str, list[int]]:
        """The CPUs each live child may run on, as the kernel says (node -> CPUs)."""
        out = {}
        for c in list(self.children):
            try:
                out[c.name] = sorted(os.sched_getaffinity(c.proc.pid))
            except (AttributeError, OSError):  # not Linux, or gone
                pass
        return out

    def cpu_since_go(self) -> None:
        """Each node's CPU seconds since "go" (``cpu_s``) up to the sim's summary line,
        or (none came yet) up to now: call it before the children are stopped and while
        an exited one is not reaped yet."""
        now = self.cpu_at_end if self.cpu_at_end is not None else self.read_cpu()
        self.cpu_s = {c.name: now[c.proc.pid] - self.cpu_at_go.get(c.proc.pid, 0.0)
                      for c in self.children if c.proc.pid in now}

    def on_ready(self, node: str, alive: bool) -> None:
        """A node's readiness token appeared (or went): the bus, not its stdout, says
        when it is ready (``bus.node.Bus.declare_ready``); a token gone (the node
        stopped or died) clears it."""
        if node in self.ready:
            (self.ready[node].set if alive else self.ready[node].clear)()

    def dead(self, exclude: str | None = None) -> Child | None:
        """The first child (other than ``exclude``) that has exited, if any."""
        for c in self.children:
            if c.name != exclude and c.proc.poll() is not None:
                return c
        return None

    def wait_for(self, event: threading.Event, what: str, timeout: float) -> Child | None:
        """Wait for ``event`` while watching the children; a dead child is returned."""
        deadline = time.monotonic() + timeout
        while not event.wait(0.05):
            if (c := self.dead()) is not None:
                return c
            if time.monotonic() > deadline:
                raise TimeoutError(f"{what} not ready within {timeout:.0f} s")
        return None

    def counter_totals(self) -> dict[str, dict[str, int]]:
        """The nodes' counters lines summed per node (over restarts), by node name."""
        with self._lock:
            return {k: dict(v) for k, v in sorted(self.counters.items())}

    def stop(self, grace: float = GRACE_S, keep: str | None = None) -> list[str]:
        """SIGTERM every live child (but ``keep``), SIGKILL what is left after ``grace``
        seconds; the names of those (see :meth:`_stop`). Their last lines (the counters)
        are read before it returns."""
        children = [c for c in self.children if c.name != keep]
        killed = self._stop(children, grace)
        for c in children:
            if c.reader is not None:
                c.reader.join(1.0)
        return killed

    @staticmethod
    def _stop(children: list[Child], grace: float) -> list[str]:
        """SIGTERM ``children``, SIGKILL those still running after ``grace`` seconds: a
        node that does not stop on SIGTERM is a bug (every node stops within 2 s), so
        they are named, on one line; returns their names."""
        for c in reversed(children):
            if c.proc.poll() is None:
                try:
                    os.killpg(c.proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + grace
        killed = []
        for c in children:
            try:
                c.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(c.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                killed.append(c.name)
                c.proc.wait(1.0)
        if killed:
            print(f"skyloop up: force-killed {', '.join(killed)} (still running "
                  f"{grace:g} s after SIGTERM)", file=sys.stderr, flush=True)
        return killed


def _security_flags(args: UpCommand) -> list[str]:
    """The MAVLink security flags of ``up`` for the bridge and the policy (same key)."""
    flags = [] if args.signing_key_file is None else ["--signing-key-file",
                                                      str(args.signing_key_file)]
    return flags + [a for n in (args.allow_sysid or []) for a in ("--allow-sysid", str(n))]


def as_trained(args: UpCommand) -> tuple[UpCommand, str | None]:
    """A copy of ``args`` that makes the state the policy's actor was trained on: its
    recorded icosahedron radius as ``--param SKY_ICO_RADIUS`` (perception's radius and the
    sim's LiDAR range) unless a ``--param`` gives it, and its encoding as perception's
    unless ``--encoding`` gives one; with a line saying so where that differs from the
    defaults (else None). ``--policy none``, the scripted controller: unchanged. An actor
    file that cannot be read is the ValueError ``skyloop up`` prints as one line."""
    if args.policy in ("none", "scripted"):
        return args, None
    from bus.params import default
    from policy.training.evaluate import ActorController

    actor = ActorController(args.actor, task=None)  # torch: read once, here
    trained, observation = actor.trained_task, actor.trained_observation
    out, said = copy.copy(args), []
    if "SKY_ICO_RADIUS" not in parse_params(args.param):
        out.param = (*args.param, f"SKY_ICO_RADIUS={trained.ico_radius:g}")
        if trained.ico_radius != default("SKY_ICO_RADIUS"):
            said.append(f"icosahedron radius {trained.ico_radius:g} m (SKY_ICO_RADIUS; "
                        f"the LiDAR's range follows)")
    if args.encoding is None:
        out.encoding = observation.encoding
        if observation.encoding != "distance":
            said.append(f"{observation.encoding} encoding")
    if trained.frames != TASK.frames:
        said.append(f"{trained.frames} frames a state")
    line = (f"skyloop up: flying {actor.name} in the state it was trained on: "
            f"{', '.join(said)}") if said else None
    return out, line


def _node_args(args: UpCommand, ports: dict[str, int]) -> dict[str, list[str]]:
    clock = ["--realtime"] if args.realtime else ["--lockstep"]
    v = ["--vehicle", args.vehicle]
    params = [a for p in args.param for a in ("--param", p)]
    security = _security_flags(args)
    return {
        "perception": ["perception", *v,
                       *(["--encoding", args.encoding] if args.encoding else [])],
        "bridge": ["bridge", *v, "--api-port", str(ports["api"]),
                   "--api-local-port", str(ports["api_local"]),
                   "--gcs-port", str(ports["gcs"]), "--gcs-local-port", str(ports["gcs_local"]),
                   *params, *security,
                   *(["--bind", "0.0.0.0", "--expose"] if args.expose else [])],
        "policy": ["policy", *v, *clock, "--api-port", str(ports["api"]), *security,
                   *(["--hold"] if args.goals == "gcs" else []),
                   *([] if args.policy in (None, "shipped") else ["--policy", args.policy])],
        "viz": ["viz", *v, "--viz", args.viz or "spawn", "--scan-every",
                str(args.viz_scan_every), "--scenario", args.scenario],
        "sim": ["sim", *v, *clock, "--scenario", args.scenario, "--episodes",
                str(args.episodes), "--seed", str(args.seed), "--max-steps", str(args.max_steps),
                "--lockstep-timeout", str(args.lockstep_timeout),
                *(["--free-flight"] if args.policy == "none" else []),
                *(["--goals-from-bus"] if args.goals == "gcs" else []), *params],
    }


def run_up(args: UpCommand) -> int:
    """Run the graph (see the module docstring); returns the exit code: 0 when the
    episodes finished, 1 when a node died or was not ready in time, 128 + the signal on
    Ctrl-C (130) or SIGTERM (143), after stopping every node and printing the summary of
    the episodes flown so far."""
    stop_on_sigterm()  # SIGTERM stops the graph as Ctrl-C does
    if args.ground_station and not args.realtime:
        print("--policy none / --goals gcs: free flight for a ground station, running "
              "--realtime")
    args = args.resolved()  # episodes and the clock as these settings imply
    args, line = as_trained(args)  # the state the actor was trained on
    if line:
        print(line, flush=True)
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.setdefault("MAVLINK20", "1")
    secure = args.zenoh_config_dir is not None  # with --router (UpCommand checks)
    endpoint = args.hub or \
        f"{'tls/localhost' if secure else 'tcp/127.0.0.1'}:{free_port()}"
    ports = {"api": args.api_port, "api_local": args.api_local_port, "gcs": args.gcs_port,
             "gcs_local": args.gcs_local_port}
    graph = Graph(env, args.verbose, plan(args.pin, lockstep=not args.realtime,
                                            beside=bool(args.log_dir or args.viz)))
    if secure:
        graph.zenoh_configs = Path(args.zenoh_config_dir).resolve()
        missing = [n for n in ("router", "launcher", *nodes_of(args))
                   if not (graph.zenoh_configs / f"{n}.json5").is_file()]
        if missing:
            raise ValueError(f"--zenoh-config-dir {args.zenoh_config_dir}: no "
                             f"{', '.join(m + '.json5' for m in missing)} (skyloop certs "
                             f"writes them)")
    nodes = _node_args(args, ports)
    t0 = time.monotonic()
    bus: Bus | None = None
    try:
        if args.router:
            env.update(SKYLOOP_ZENOH_MODE="client", SKYLOOP_ZENOH_CONNECT=endpoint)
            env.pop("SKYLOOP_ZENOH_LISTEN", None)
            nodes["router"] = ["router", "--listen", endpoint]
            router = graph.start("router", nodes["router"])
            if not _wait_listening(endpoint, router, 30.0):
                return _died(graph, router)
        else:
            env.update(SKYLOOP_ZENOH_MODE="peer", SKYLOOP_ZENOH_HUB=endpoint)
            env.pop("SKYLOOP_ZENOH_CONNECT", None)
        # Everything starts at once (imports take seconds); the sim warms up, then waits
        # for "go" until every node's readiness token is on the bus (ready_waits).
        if args.log_dir:
            graph.start("record", ["record", "--out", str(args.log_dir), "--vehicle",
                                   args.vehicle, "--split-episodes",
                                   str(args.log_split_episodes), "--split-minutes",
                                   str(args.log_split_minutes), "--compression",
                                   args.log_compression, "--scenario", args.scenario])
        if args.viz:
            graph.start("viz", nodes["viz"])
        for name in ("perception", "bridge"):
            graph.start(name, nodes[name])
        if args.policy != "none":
            graph.start("policy", nodes["policy"])
        sim = graph.start("sim", [*nodes["sim"], "--wait-go"], stdin=subprocess.PIPE)
        # The launcher watches the nodes' readiness tokens from a session of its own,
        # opened after the last child started (no fork with a session open); the watch
        # sees tokens declared before it too.
        bus = Bus.open(replace(SessionConfig.from_env(env), config_file=str(
            graph.zenoh_configs / "launcher.json5")) if secure else SessionConfig.from_env(env))
        bus.watch_ready(args.vehicle, graph.on_ready)  # this stack's vehicle only
        for name, timeout in ready_waits(args):
            if (c := graph.wait_for(graph.ready[name], name, timeout)) is not None:
                return _died(graph, c)
        assert sim.proc.stdin is not None
        graph.cpu_at_go = graph.read_cpu()  # what start-up and warm-up cost stays out
        graph.cpus = graph.affinity()
        sim.proc.stdin.write("go\n")
        sim.proc.stdin.flush()
        bus.close()  # readiness is known; a restart forks, never with a session open
        bus = None
        while not exited(sim.proc):
            if (c := graph.dead(exclude="sim")) is not None:
                if not _may_restart(graph, c, args):
                    return _died(graph, c)
                graph.restart(c, nodes[c.name])
                for name in RESTARTABLE[c.name]:
                    if (along := graph.child(name)) is not None:
                        print(f"skyloop up: restarting '{name}' too (it depends on "
                              f"'{c.name}')", file=sys.stderr, flush=True)
                        graph.restart(along, nodes[name])
            time.sleep(0.05)
        graph.cpu_since_go()  # before the others stop, the sim not reaped yet
        sim.proc.poll()
        if sim.reader is not None:  # its last lines (the summary) read before judging it
            sim.reader.join(5.0)
        if sim.proc.returncode != 0 or graph.summary is None:
            return _died(graph, sim)
        graph.stop(keep="viz" if args.viz == "web" else None)
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
        print(f"{signal.Signals(signum).name}: stopping every node", file=sys.stderr,
              flush=True)
        if graph.cpu_at_go:  # the run had started: where its time went so far
            graph.cpu_since_go()
        graph.stop()
        if graph.summary is not None:  # written as at the end: what was flown so far
            _write_json(args, _summary(graph, args, time.monotonic() - t0))
        else:
            print(f"summary: {len(graph.episodes)} episodes finished before the stop",
                  flush=True)
            _write_json(args, {"episodes": len(graph.episodes), "stopped_by": signum,
                               "counters": graph.counter_totals()})
        return 128 + signum
    except TimeoutError as err:
        graph.stop()
        print(f"skyloop up: {err}", file=sys.stderr, flush=True)
        return 1
    except Exception:  # e.g. the launcher's own Zenoh session failed: no orphans
        graph.stop()
        raise
    finally:  # every return above stopped the nodes first
        if bus is not None:
            bus.close()
    _write_json(args, _summary(graph, args, time.monotonic() - t0))
    if args.viz == "web":  # the run is over; its view stays until Ctrl-C or SIGTERM
        print("the web viewer keeps the run (address above): Ctrl-C to stop", flush=True)
        try:
            while graph.dead() is None:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        graph.stop()
    return 0


def nodes_of(args: UpCommand) -> list[str]:
    """The nodes ``skyloop up`` starts for these flags (the router aside)."""
    return [*(["record"] if args.log_dir else []), *(["viz"] if args.viz else []),
            "perception", "bridge",
            *(["policy"] if args.policy != "none" else []), "sim"]


def ready_waits(args: UpCommand) -> list[tuple[str, float]]:
    """The readiness tokens ``skyloop up`` waits for before "go", in order, each with
    its timeout (s, from when the wait for it starts): one per node of
    :func:`nodes_of`, the slowest starters (the sim warms up, the policy loads torch and
    takes off) first."""
    return [(n, READY_TIMEOUT_S[n]) for n in sorted(nodes_of(args), key=READY_NODES.index)]


def _wait_listening(endpoint: str, child: Child, timeout: float) -> bool:
    """Wait until ``tcp/host:port`` accepts connections (False if ``child`` died)."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while child.proc.poll() is None:
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex((host, int(port))) == 0:
                return True
        if time.monotonic() > deadline:
            raise TimeoutError(f"router not listening on {endpoint} within {timeout:.0f} s")
        time.sleep(0.02)
    return False


def _may_restart(graph: Graph, child: Child, args: UpCommand) -> bool:
    """``--restart on-failure``: whether ``child`` (exited) is started again; says so."""
    code = child.proc.returncode
    n = graph.restarts[child.name]
    if args.restart != "on-failure" or child.name not in RESTARTABLE or code == 0 \
            or n >= args.max_restarts:
        return False
    print(f"skyloop up: node '{child.name}' exited (code {code}); its last log line: "
          f"{child.last_line}; restarting it ({n + 1}/{args.max_restarts})",
          file=sys.stderr, flush=True)
    return True


def _died(graph: Graph, child: Child) -> int:
    child.proc.poll()
    code = child.proc.returncode
    graph.stop()
    print(f"skyloop up: node '{child.name}' exited (code {code}); its last log line: "
          f"{child.last_line}", file=sys.stderr, flush=True)
    return 1


def _summary(graph: Graph, args: UpCommand, wall_s: float) -> dict[str, Any]:
    s = dict(graph.summary or {})
    n = s.get("episodes", 0)
    s.update(policy=args.policy or "shipped", router=bool(args.router), log=graph.log_path,
             total_wall_s=wall_s, restarts=dict(graph.restarts), cpus=graph.cpus,
             pinned=graph.placement is not None)
    outcomes = ("success", "collision", "timeout") + (("aborted",) if s.get("aborted") else ())
    rates = ", ".join(f"{o} {s.get(o, 0)}/{n}" for o in outcomes)
    lat = (f", latency p50 {s['latency_ms_p50']:.2f} ms p99 {s['latency_ms_p99']:.2f} ms"
           if "latency_ms_p50" in s else "")
    restarts = ("; restarted " + ", ".join(f"{k} {v}x" for k, v in graph.restarts.items())
                if graph.restarts else "")
    print(f"summary: {n} episodes on {s.get('scenario')} ({s.get('mode')}): {rates}; "
          f"mean steps {s.get('mean_steps', 0):.1f}; {s.get('steps_per_s', 0):.0f} control "
          f"steps/s{lat}{restarts}", flush=True)
    steps = s.get("steps", 0)
    if graph.cpu_s and steps:
        s["cpu_ms_per_step"] = {k: round(v * 1e3 / steps, 3) for k, v in graph.cpu_s.items()}
        per = ", ".join(f"{k} {v:.2f}" for k, v in s["cpu_ms_per_step"].items())
        print(f"cpu per control step after go (ms): {per}; total "
              f"{sum(s['cpu_ms_per_step'].values()):.2f}", flush=True)
    if graph.placement is not None:
        chain = [n for n in graph.cpus if graph.placement.cpus(n) is not None]
        cores = sorted(graph.placement.chain)
        print(f"pinned (--pin): the chain ({', '.join(chain)}) shares CPU "
              f"{', '.join(map(str, cores))}", flush=True)
    if graph.counters:
        s["counters"] = graph.counter_totals()
        # each node's counters (SKYLOOP-COUNTERS) say what its bounded queues dropped
        drops = ", ".join(f"{k} {v['dropped']}" for k, v in s["counters"].items()
                          if "dropped" in v)
        print(f"dropped from bounded queues (overload): {drops}", flush=True)
        router = s["counters"].get("router", {})
        if router.get("denied"):  # what its access control refused (bus.denials)
            kinds = ", ".join(f"{k.removeprefix('denied_').replace('_', ' ')} {v}"
                              for k, v in sorted(router.items()) if k.startswith("denied_"))
            print(f"refused by the router's access control: {router['denied']} message(s) "
                  f"({kinds}); the router's output (-v) names the keys", flush=True)
        refusals = s["counters"].get("policy", {}).get("refusals", 0)
        if refusals:
            print(f"the policy held the vehicle {refusals} time(s): a vehicle parameter or "
                  f"perception's encoding differed from what its actor was trained with "
                  f"(its STATUSTEXT and log say which)", flush=True)
    if graph.log_path:
        print(f"log: {graph.log_path}", flush=True)
    return s


def _write_json(args: UpCommand, summary: dict[str, Any]) -> None:
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=2))


def counters_line(counters: dict[str, int]) -> str:
    """A node's last line for the launcher (:data:`COUNTERS_LINE`): its counters, with
    ``dropped`` (what its bounded queues dropped) among them."""
    return COUNTERS_LINE + json.dumps(counters, sort_keys=True)
