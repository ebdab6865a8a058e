"""The env's fast rgb_array renderer (sitl.render.frames): frame, content, RecordVideo.

Speed is measured in benchmarks/bench_env.py (``render_fps``), not asserted here.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from policy.training.env import EnvConfig, UavNavEnv
from sitl.episode import EpisodeConfig
from sitl.render.frames import FRONT, FastRenderer
from sitl.world.obstacles import box_solid
from sitl.world.world import World


@pytest.fixture(scope="module")
def valley() -> World:
    return World("valley")


def _yaw(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_env_frame_shape_and_terrain_covers_the_map() -> None:
    env = UavNavEnv(scenario="valley", render_mode="rgb_array")
    env.reset(seed=1)
    env.step(np.array([1.0, 0.0, 0.0, 0.0]))
    frame = env.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    view = frame[:, :480].astype(int)
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    # terrain (greens, tans, browns, shaded or dimmed): blue is the weakest channel
    terrain_like = (b <= g) & (b <= r + 30) & (view.sum(-1) > 60)
    assert terrain_like.mean() > 0.8
    assert len(np.unique(view.reshape(-1, 3), axis=0)) > 1000  # shaded, not flat colours
    assert frame[:, 480:].std() > 10  # the panel is drawn
    env.close()


def test_vehicle_is_drawn_where_it_is(valley: World) -> None:
    r = FastRenderer(valley)
    a, b = np.array([-8.0, -5.0, 3.5]), np.array([6.0, 9.0, 3.5])
    fa, fb = r.frame(position=a), r.frame(position=b)
    changed = np.argwhere(np.any(fa != fb, axis=-1))  # (row, col)
    assert len(changed) > 100
    pa, pb = r.to_px(a[:2]), r.to_px(b[:2])
    on_map = changed[changed[:, 1] < r.map_px]
    da = np.hypot(on_map[:, 1] - pa[0], on_map[:, 0] - pa[1])
    db = np.hypot(on_map[:, 1] - pb[0], on_map[:, 0] - pb[1])
    assert np.all(np.minimum(da, db) <= 20)  # only around the two places (icon: 16 px)
    assert (da <= 20).sum() > 50 and (db <= 20).sum() > 50
    # and nothing else on the map: the base is untouched away from the vehicle
    far = np.ones(fa.shape[:2], bool)
    far[:, r.map_px:] = False
    for p in (pa, pb):
        far[max(int(p[1]) - 24, 0):int(p[1]) + 24, max(int(p[0]) - 24, 0):int(p[0]) + 24] = 0
    assert np.array_equal(fa[far], r.base[far])


def test_heading_points_the_nose(valley: World) -> None:
    r = FastRenderer(valley)
    pos = np.array([0.0, 0.0, 3.5])
    c = r.to_px(pos[:2])
    for yaw in (0.0, math.pi / 2, -2.5):
        frame = r.frame(position=pos, rotation=_yaw(yaw))
        rows, cols = np.nonzero(np.all(frame[:, : r.map_px] == FRONT, axis=-1))
        dx, dy = cols.mean() - c[0], -(rows.mean() - c[1])  # rows run south
        assert math.cos(math.atan2(dy, dx) - yaw) > 0.95


def test_trail_goal_points_faces_and_aircraft_are_drawn() -> None:
    world = World("dynamic")
    normals = np.random.default_rng(0).normal(size=(32, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    r = FastRenderer(world, face_normals=normals)
    pos = np.array([0.0, -12.0, 3.5])
    bare = r.frame(position=pos)
    path = np.array([[-10.0, -12.0, 3.5], [-5.0, -12.0, 3.5], pos])
    pts = np.array([[2.0, 0.0, 0.0], [0.0, -3.0, 0.5], [1.5, 1.5, -1.0]])
    full = r.frame(position=pos, path=path, goal=np.array([10.0, 10.0, 3.5]),
                   start=path[0], points=pts, face_values=np.linspace(0, 4, 32),
                   velocity=np.array([1.0, 0.0, 0.0]), step=3)
    diff = np.any(bare != full, axis=-1)
    for xy in (path[1, :2], [10.0, 10.0], pos[:2] + [2.0, 0.0]):  # trail, goal, a return
        c, rr = (int(v) for v in r.to_px(np.asarray(xy)))
        assert diff[rr - 3:rr + 4, c - 3:c + 4].any(), xy
    assert diff[:, r.map_px:].sum() > 500  # face charts, charts and labels in the panel
    # aircraft move with t
    later = r.frame(position=pos, t=5.0)
    moved = np.any(bare != later, axis=-1)
    for x, y in world.aircraft_positions(5.0)[:, :2]:
        c, rr = (int(v) for v in r.to_px(np.array([x, y])))
        if 0 <= c < r.map_px and 0 <= rr < r.map_px:
            assert moved[max(rr - 4, 0):rr + 5, max(c - 4, 0):c + 5].any()


def test_outcome_border_and_renderer_cache() -> None:
    env = UavNavEnv(scenario="valley", render_mode="rgb_array")
    env.reset(seed=2)
    env.render()
    first = env._renderer
    env.reset(seed=3)
    env.render()
    assert env._renderer is first  # same world: the precomputed map is reused
    env.world.add_solids([box_solid(np.array([0.0, 0.0, 2.0]), np.array([1.0, 1.0, 2.0]))])
    env.render()
    assert env._renderer is not first  # the world changed: a new map
    img = env._renderer.frame(position=env.start, outcome="collision")
    assert np.all(img[:4, :480] == img[0, 0]) and img[0, 0, 0] > 200 and img[0, 0, 1] < 80
    with pytest.raises(ValueError, match="render_backend"):
        UavNavEnv(render_backend="opengl")


def test_matplotlib_backend_is_still_reachable() -> None:
    env = UavNavEnv(scenario="valley", render_mode="rgb_array", render_backend="matplotlib")
    env.reset(seed=1)
    frame = env.render()
    assert frame.shape == (480, 960, 3) and frame.dtype == np.uint8


def test_record_video_writes_an_episode(tmp_path: Path) -> None:
    pytest.importorskip("moviepy", reason="the video extra: pip install -e '.[video]'")
    import imageio_ffmpeg
    from gymnasium.wrappers import RecordVideo

    steps = 12
    config = EnvConfig(max_steps=steps, episode=EpisodeConfig(scenario="valley"))
    env = RecordVideo(UavNavEnv(render_mode="rgb_array", config=config),
                      str(tmp_path / "videos"), episode_trigger=lambda _: True,
                      name_prefix="uav")
    env.reset(seed=4)
    done, n = False, 0
    while not done:
        _, _, term, trunc, _ = env.step(np.array([0.5, 0.0, 0.0, 0.2], np.float32))
        done, n = term or trunc, n + 1
    env.close()
    videos = sorted((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(videos[0]))
    assert frames == n + 1  # the reset frame and one a step
