"""The world of a scenario: terrain, static obstacles, moving aircraft, collision.

Geometry is generated once from the scenario's own ``seed``. Generation is checked
for solvability: at the flight level, the free space (cells where the UAV body
fits, see :data:`UAV_BODY_RADIUS`) inside the navigable area must be one connected
region holding at least ``MIN_CONNECTED`` of the free cells; otherwise the generator
draws again from the same RNG stream (deterministic). Starts and goals are drawn
only from that connected region, so every episode has a collision-free path at the
flight level (it may have to go around hills, trees or buildings).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import ndimage

from sitl.world import collide
from sitl.world.aircraft import Fleet
from sitl.world.obstacles import (
    ConvexSolid,
    generate_buildings,
    generate_trees,
    merge_meshes,
    pack_solids,
)
from sitl.world.scenario import Scenario, ScenarioError, load_scenario, scenario_names
from sitl.world.terrain import Heightfield, generate_terrain

__all__ = [
    "UAV_BODY_RADIUS",
    "Scenario",
    "ScenarioError",
    "World",
    "load_scenario",
    "scenario_names",
]

# F450 body sphere: arm 0.1651 m (centre to motor axis, as in the JSBSim F450 model)
# + propeller radius ~0.12 m (9.4 inch props) = 0.285 m, rounded up to 0.3 m.
UAV_BODY_RADIUS = 0.3

MIN_CONNECTED = 0.9  # share of free flight-level cells in the main connected region
MAX_ATTEMPTS = 20


class World:
    """Terrain + obstacles + aircraft of one scenario, with fast collision queries."""

    def __init__(self, scenario: Scenario | str | Path) -> None:
        if not isinstance(scenario, Scenario):
            scenario = load_scenario(scenario)
        self.scenario = scenario
        a = scenario.area
        self.flight_level: float = a.flight_level
        self.bounds: tuple[float, float, float, float] = (
            -a.size_x / 2, a.size_x / 2, -a.size_y / 2, a.size_y / 2)
        self.extent = (self.bounds[0] - a.margin, self.bounds[1] + a.margin,
                       self.bounds[2] - a.margin, self.bounds[3] + a.margin)
        self.fleet = Fleet.from_config(scenario.aircraft)
        rng = np.random.default_rng(scenario.seed)
        attempts = 0
        while attempts < MAX_ATTEMPTS:
            attempts += 1
            self._generate(rng)
            if self.connected_share >= MIN_CONNECTED:
                break
        if self.connected_share < MIN_CONNECTED:
            raise ScenarioError(
                f"{Path(scenario.source).name or scenario.name}: field 'seed': no passable "
                f"world in {MAX_ATTEMPTS} draws (main free region "
                f"{self.connected_share:.0%} < {MIN_CONNECTED:.0%}); lower obstacle counts"
            )
        self.generation_attempts = attempts
        self._sampling_cells()

    # --- generation --------------------------------------------------------------

    def _generate(self, rng: np.random.Generator) -> None:
        s = self.scenario
        self.terrain: Heightfield = generate_terrain(s.terrain, self.extent, rng, self.bounds)
        self.solids: list[ConvexSolid] = (
            generate_buildings(s.buildings, self.bounds, self.terrain, rng)
            + generate_trees(s.trees, self.bounds, self.terrain, rng)
        )
        self.packed = pack_solids(self.solids)
        self._static_args = (self.terrain.heights, self.terrain.x0, self.terrain.y0,
                             self.terrain.res, self.packed.planes, self.packed.start,
                             self.packed.aabb, self.packed.box)
        self._air_args = (self.fleet.waypoints, self.fleet.cumlen, self.fleet.count,
                          self.fleet.params)
        self._free_grid()

    def _free_grid(self) -> None:
        """Flight-level grid: where the body fits, and the main connected free region."""
        res = self.terrain.res
        xmin, xmax, ymin, ymax = self.bounds
        self.grid_x = np.arange(xmin + res / 2, xmax, res)
        self.grid_y = np.arange(ymin + res / 2, ymax, res)
        gx, gy = np.meshgrid(self.grid_x, self.grid_y)
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, self.flight_level)])
        self._grid_pts = pts
        # res/2 margin: neighbouring free centres are joined by a free segment
        hit = collide.points_collide_static(pts, UAV_BODY_RADIUS + res / 2, *self._static_args)
        free = ~hit.reshape(gx.shape)
        self.free = free
        labels, n = ndimage.label(free)
        if n == 0:
            self.main_region = np.zeros_like(free)
            self.connected_share = 0.0
            return
        sizes = np.bincount(labels.ravel())[1:]
        self.main_region = labels == (np.argmax(sizes) + 1)
        self.connected_share = float(sizes.max() / sizes.sum())

    def _sampling_cells(self) -> None:
        sg = self.scenario.start_goal
        pts = self._grid_pts
        clear = ~collide.points_collide_static(pts, max(sg.clearance, UAV_BODY_RADIUS),
                                                 *self._static_args)
        low = self.terrain.height(pts[:, 0], pts[:, 1]) <= sg.max_terrain_height
        ok = self.main_region.ravel() & clear & low
        self.candidates = pts[ok]
        if len(self.candidates) < 2:
            raise ScenarioError(f"{self.scenario.source or self.scenario.name}: field "
                                "'start_goal.clearance': no place for a start and a goal")

    def add_solids(self, solids: list[ConvexSolid]) -> None:
        """Add static obstacles (e.g. a test box); build LiDARs after adding them."""
        self.solids = self.solids + list(solids)
        self.packed = pack_solids(self.solids)
        p = self.packed
        self._static_args = self._static_args[:4] + (p.planes, p.start, p.aabb, p.box)
        self._free_grid()
        self._sampling_cells()

    # --- queries -----------------------------------------------------------------

    def terrain_height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Terrain height (m above datum) at (x, y); scalars in, float out."""
        return self.terrain.height(x, y)

    def collides(self, position: np.ndarray, radius: float, t: float) -> bool:
        """True if a sphere at ``position`` touches terrain, an obstacle or an aircraft."""
        return bool(collide.collides_all(float(position[0]), float(position[1]),
                                         float(position[2]), float(radius), float(t),
                                         *self._static_args, *self._air_args))

    def collides_off_terrain(self, position: np.ndarray, radius: float, t: float) -> bool:
        """Like :meth:`collides` without the terrain: obstacles and aircraft only (a
        vehicle standing or landing on the terrain touches it without crashing)."""
        x, y, z, r = float(position[0]), float(position[1]), float(position[2]), float(radius)
        return bool(collide.sphere_hits_solids(x, y, z, r, *self._static_args[4:])
                    or collide.sphere_hits_aircraft(x, y, z, r, float(t), *self._air_args))

    def collides_static(self, position: np.ndarray, radius: float) -> bool:
        """Like :meth:`collides` without the aircraft."""
        return bool(collide.collides_static(float(position[0]), float(position[1]),
                                            float(position[2]), float(radius),
                                            *self._static_args))

    def straight_line_blocked(self, start: np.ndarray, goal: np.ndarray,
                              radius: float = UAV_BODY_RADIUS) -> bool:
        """True if the body swept straight from start to goal hits static geometry."""
        step = min(0.1, radius / 2) if radius > 0 else 0.05
        return bool(collide.segment_blocked(np.asarray(start, float), np.asarray(goal, float),
                                            float(radius), step, *self._static_args))

    def sample_start_goal(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A random start and goal at the flight level, ``start_goal`` rules applied.

        Both lie in the main connected free region (so a path exists), keep
        ``clearance`` from terrain, obstacles and (at t = 0) aircraft, have terrain
        no higher than ``max_terrain_height`` below them, and are between
        ``min_distance`` and ``max_distance`` apart.
        """
        sg = self.scenario.start_goal
        cand, res = self.candidates, self.terrain.res
        clearance = max(sg.clearance, UAV_BODY_RADIUS)
        for _ in range(1000):
            start = self._jitter(cand[rng.integers(len(cand))], rng, res)
            if self.collides(start, clearance, 0.0):
                continue
            d = np.hypot(cand[:, 0] - start[0], cand[:, 1] - start[1])
            ok = np.flatnonzero((d >= sg.min_distance) & (d <= sg.max_distance))
            if len(ok) == 0:
                continue
            for _ in range(20):
                goal = self._jitter(cand[ok[rng.integers(len(ok))]], rng, res)
                dist = math.hypot(goal[0] - start[0], goal[1] - start[1])
                if (sg.min_distance <= dist <= sg.max_distance
                        and not self.collides(goal, clearance, 0.0)):
                    return start, goal
        raise RuntimeError(f"{self.scenario.name}: could not sample a start and goal")

    def _jitter(self, p: np.ndarray, rng: np.random.Generator, res: float) -> np.ndarray:
        q = p.copy()
        q[:2] += rng.uniform(-res / 2, res / 2, size=2)
        return q

    # --- aircraft and geometry for the LiDAR / renderer ----------------------------

    def aircraft_positions(self, t: float) -> np.ndarray:
        """(K,3) aircraft centres at time t."""
        return self.fleet.poses(t)[:, :3]

    def aircraft_boxes(self, t: float) -> np.ndarray:
        """(K,8) aircraft boxes (cx, cy, cz, hx, hy, hz, cos yaw, sin yaw) at time t."""
        return self.fleet.boxes(t)

    def static_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Terrain + obstacle triangles: vertices (V,3) float32, triangles (T,3) int32."""
        return merge_meshes([self.terrain.mesh()] + [(s.vertices, s.triangles)
                                                      for s in self.solids])
