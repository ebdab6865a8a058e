"""The geometry the log's 3D view shows, read from the simulator's world and from
perception's icosahedron (:class:`SitlScene`, a :class:`bus.ros.view.SceneSource`), and
the process that builds worlds for a recorder (:class:`WorldWorker`).

``bus`` imports nothing internal at import time (``../shared/DESIGN.md``); this module is
the one place where the recorder reads ``sitl`` and ``perception``, and only inside
methods, off the writer thread: the world is deterministic from the scenario name an
EpisodeEvent START carries (``World(load_scenario(name))``), so the recorder rebuilds
the very geometry the simulator flies in instead of the bus carrying it. Without those
packages (a recorder installed alone) the view still writes TF, clock, path and goal;
the world, aircraft and icosahedron markers are counted as ``scene_errors``.

Worlds are built in a child process, ``python -m bus.ros.scene`` (:class:`WorldWorker`):
building one takes about 1 s of CPU, much of it in calls that hold the interpreter lock
(numba, qhull); on a thread of the recorder that starved its writer thread, whose
bounded queue then dropped messages (seen: 175 of one run on a loaded machine). The
worker reads scenario names, one a line, on stdin and answers each on stdout with a
frame: status (uint8, 0 ok), name length (uint16), data length (uint32), little-endian,
then the name and the CDR bytes of the world's MarkerArray (or the error text). It
builds the run's scenario (``--prebuild``: what ``skyloop record --scenario`` gives, which
``skyloop up`` passes; valley without one; a family's template only) as soon as it
starts, and each world once. It runs in a session of its own, so the signals that stop the recorder
(the launcher's to the recorder's process group, a terminal's Ctrl-C) do not reach it:
a world being built at stop can still be written; it exits when the recorder closes
the pipe or dies (end of input).
"""

from __future__ import annotations

import argparse
import logging
import os
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from typing import IO, Any

import numpy as np

from bus.ros.view import Mesh, WorldGeometry, WorldRequest, decimate_heightfield

log = logging.getLogger("skyloop.record")
_FRAME = struct.Struct("<BHI")


class SitlScene:
    """Scenario geometry from ``sitl.world.world`` and the icosahedron from
    ``perception.icosahedron``; the terrain decimated to at most ``max_terrain_triangles``
    (:func:`bus.ros.view.decimate_heightfield`; the scenarios' 55 m square at 0.25 m is
    96,800 triangles; at 4,000 the valley's stays within 0.24 m of it, forest's and
    city's within 2 cm with fewer). ``terrain_error``: the last world's worst error (m)."""

    def __init__(self, max_terrain_triangles: int = 4000) -> None:
        self.max_terrain_triangles = max_terrain_triangles
        self.terrain_error = float("nan")

    def warm(self) -> None:
        """What the recorder's own process needs: the icosahedron's module and the
        aircraft kernel's first call (numba, ~0.4 s), off the writer thread."""
        import perception.icosahedron  # noqa: F401
        from sitl.world.aircraft import aircraft_pose

        aircraft_pose(np.zeros((1, 2, 3)), np.zeros((1, 2)), np.array([2]), np.zeros((1, 6)),
                      0, 0.0)


    def aircraft(self, scenario: str) -> Callable[[float], np.ndarray] | None:
        from sitl.world.aircraft import Fleet
        from sitl.world.scenario import load_scenario

        fleet = Fleet.from_config(load_scenario(scenario).aircraft)
        return fleet.boxes if len(fleet) else None

    def world(self, scenario: str) -> WorldGeometry:
        from sitl.world.world import UAV_BODY_RADIUS, World, load_scenario

        world = World(load_scenario(scenario))
        t = world.terrain
        terrain, self.terrain_error = decimate_heightfield(t.heights, t.x0, t.y0, t.res,
                                                           self.max_terrain_triangles)

        def solids(*kinds: str) -> Mesh:
            return Mesh.merge([(s.vertices, s.triangles) for s in world.solids
                               if s.kind in kinds])

        return WorldGeometry(terrain=terrain, buildings=solids("building"),
                             trunks=solids("trunk"), crowns=solids("crown"),
                             body_radius=UAV_BODY_RADIUS)

    def icosahedron(self) -> tuple[np.ndarray, list[list[int]]]:
        from perception.icosahedron import TruncatedIcosahedron

        ico = TruncatedIcosahedron(1.0)
        return np.asarray(ico.vertices), [list(f) for f in ico.faces]


class WorldWorker:
    """``python -m bus.ros.scene`` as a child process building world markers (see the
    module docstring); :meth:`request` returns a :class:`~bus.ros.view.WorldRequest`
    that a reader thread completes. The child runs in a session of its own, so
    the recorder's stop signals do not end it before the recorder is done with it;
    :meth:`close` does (and the end of the recorder: its input ends)."""

    def __init__(self, max_terrain_triangles: int = 4000,
                 prebuilt: Sequence[str] = ()) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "bus.ros.scene", "--max-terrain-triangles",
             str(max_terrain_triangles), *(["--prebuild", *prebuilt] if prebuilt else [])],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, start_new_session=True)
        self._lock = threading.Lock()
        self._pending: dict[str, WorldRequest] = {}
        threading.Thread(target=self._read, name="skyloop-record-worlds", daemon=True).start()

    def request(self, scenario: str) -> WorldRequest:
        with self._lock:
            req = self._pending.get(scenario)
            if req is not None:
                return req
            req = self._pending[scenario] = WorldRequest()
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write(scenario.encode() + b"\n")
            self.proc.stdin.flush()
        except (OSError, ValueError) as err:  # the worker is gone
            self._finish(scenario, None, RuntimeError(f"world worker: {err}"))
        return req

    def _finish(self, scenario: str, data: bytes | None, error: BaseException | None) -> None:
        with self._lock:
            req = self._pending.pop(scenario, None)
        if req is not None:
            req.set(data, error)

    def _read(self) -> None:
        out = self.proc.stdout
        assert out is not None
        try:
            while True:
                head = out.read(_FRAME.size)
                if len(head) < _FRAME.size:
                    break
                status, n_name, n_data = _FRAME.unpack(head)
                name = out.read(n_name).decode()
                data = out.read(n_data)
                if status == 0:
                    self._finish(name, data, None)
                else:
                    self._finish(name, None, RuntimeError(data.decode(errors="replace")))
        except (OSError, ValueError):
            pass
        with self._lock:
            pending, self._pending = self._pending, {}
        for req in pending.values():
            req.set(None, RuntimeError("world worker exited"))

    def close(self) -> None:
        """End the child: its stdin closes (it exits between builds), killed if it is
        still there after 0.2 s (inside a build)."""
        try:
            if self.proc.stdin is not None:
                self.proc.stdin.close()
            self.proc.wait(0.2)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


#: Built by the worker as soon as it starts, before any request, unless it is given the
#: scenario(s) to expect (``skyloop record --scenario``, which ``skyloop up`` passes):
#: ``skyloop up``'s default scenario, so that its markers are ready at the first START
#: (building one also warms the imports and numba kernels every other world needs).
PREBUILT = ("valley",)


def serve(stdin: IO[bytes], stdout: IO[bytes], scene: Any,
          prebuilt: Sequence[str] = PREBUILT) -> None:
    """The worker's loop: a scenario name a line in, a frame (module docstring) out;
    the markers of each scenario built once."""
    from bus.messages import encode
    from bus.ros.view import world_markers

    built: dict[str, bytes] = {}

    def build(name: str) -> bytes:
        if name not in built:
            built[name] = encode(world_markers(scene.world(name)))
        return built[name]

    from sitl.world.families import WorldSource

    for name in prebuilt:
        try:
            source = WorldSource.parse(name)
            if source.fixed:
                build(name)
            else:  # a family or a mixture draws its worlds: its template warms the kernels
                scene.world(source.template())
        except Exception:  # noqa: BLE001 - a request for it reports the failure
            log.exception("world worker: building %s failed", name)
    for line in stdin:
        name = line.decode().strip()
        if not name:
            continue
        try:
            status, data = 0, build(name)
        except Exception as err:  # noqa: BLE001 - answered, the recorder counts it
            status, data = 1, f"{type(err).__name__}: {err}".encode()
        raw = name.encode()
        stdout.write(_FRAME.pack(status, len(raw), len(data)) + raw + data)
        stdout.flush()


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bus.ros.scene",
                                description="Build world markers for a recorder (stdin: "
                                            "scenario names; stdout: framed CDR).")
    p.add_argument("--max-terrain-triangles", type=int, default=4000)
    p.add_argument("--prebuild", nargs="+", default=list(PREBUILT), metavar="SCENARIO",
                   help="build these before the first request (default: %(default)s)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        serve(sys.stdin.buffer, sys.stdout.buffer, SitlScene(args.max_terrain_triangles),
              args.prebuild)
    except (KeyboardInterrupt, BrokenPipeError):
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
