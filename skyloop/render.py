"""``skyloop render``: a picture of a scenario with one LiDAR scan and its icosahedron faces.

The scan is taken at the episode's start pose (full range, so the picture shows what
the sensor sees); the faces come from the same reduction the policy sees.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from perception.faces import face_values
from perception.icosahedron import TruncatedIcosahedron
from sitl.lidar.scanner import Lidar, LidarConfig
from sitl.render.scene import render_scene
from sitl.world.world import World, load_scenario


def render_scenario(scenario: str, seed: int, out: Path) -> Path:
    world = World(load_scenario(scenario))
    rng = np.random.default_rng(seed)
    start, goal = world.sample_start_goal(rng)
    direction = goal[:2] - start[:2]
    yaw = float(np.arctan2(direction[1], direction[0]))
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    points = Lidar(world, LidarConfig(), seed=seed).scan(start, rotation, 0.0)
    ico = TruncatedIcosahedron()
    faces = face_values(points, ico)
    out.parent.mkdir(parents=True, exist_ok=True)
    render_scene(world, start=start, goal=goal, position=start, rotation=rotation,
                 points=points, face_values=faces, face_normals=ico.normals,
                 title=f"{scenario}, seed {seed}: {len(points)} LiDAR returns", out=out)
    return out
