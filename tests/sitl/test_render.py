"""Scene renderer: image shape, PNG output, content, speed."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np

from sitl.lidar.scanner import Lidar, LidarConfig
from sitl.render.scene import render_scene
from sitl.world.world import World


def test_render_full_scene(tmp_path: Path) -> None:
    w = World("dynamic")
    start, goal = w.sample_start_goal(np.random.default_rng(0))
    pos = start + 0.3 * (goal - start)
    rot = np.eye(3)
    pts = Lidar(w, LidarConfig(max_range=100.0)).scan(pos, rot, 2.0)
    normals = np.random.default_rng(1).normal(size=(32, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    values = np.linspace(0, 4, 32)
    out = tmp_path / "pics" / "scene.png"
    render_scene(w, start=start, goal=goal, position=pos, rotation=rot, points=pts,
                 face_values=values, face_normals=normals, paths=[np.array([start, pos])],
                 title="test", out=out, t=2.0)  # a second render reuses fonts, colormaps
    img = render_scene(w, start=start, goal=goal, position=pos, rotation=rot, points=pts,
                       face_values=values, face_normals=normals,
                       paths=[np.array([start, pos])], title="test", out=out, t=2.0)
    assert img.shape == (600, 1200, 3) and img.dtype == np.uint8
    assert out.is_file()
    png = mpimg.imread(out)
    assert png.shape[:2] == (600, 1200)
    # not blank: many distinct colours, both halves drawn
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 500
    for half in (img[:, :600], img[:, 600:]):
        assert half.std() > 20


def test_render_without_uav_and_with_polygons(tmp_path: Path) -> None:
    w = World("city")
    s, g = w.sample_start_goal(np.random.default_rng(2))
    img = render_scene(w, start=s, goal=g, paths=[np.array([s, g])], size=(800, 400))
    assert img.shape == (400, 800, 3)
    square = [np.array([[3.0, -1, -1], [3.0, 1, -1], [3.0, 1, 1], [3.0, -1, 1]])]
    img2 = render_scene(w, position=s, rotation=np.eye(3), face_values=np.array([2.0]),
                        face_polygons=square, out=tmp_path / "p.png", size=(640, 320))
    assert img2.shape == (320, 640, 3) and (tmp_path / "p.png").is_file()
    assert not np.array_equal(img2[:, 320:], np.full_like(img2[:, 320:], 255))
