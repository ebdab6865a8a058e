"""The 3D view (skyloop.viewer, Rerun): live from the bus (``skyloop up --viz``), from a
log (``skyloop view``), and the web viewer drawing it in a real headless browser."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from loopback import up_args

from bus.ros.view import face_colours, fan_triangles
from skyloop.launcher import free_port
from skyloop.viewer import parse_target

ROOT = Path(__file__).resolve().parents[2]
SKYLOOP = [sys.executable, "-m", "skyloop"]
#: what every view of a flown episode holds
ENTITIES = {"/world/terrain", "/world/obstacles", "/world/vehicle", "/world/vehicle/body",
            "/world/vehicle/lidar", "/world/vehicle/faces", "/world/trail", "/world/goal",
            "/world/cmd", "/plots/altitude", "/plots/speed", "/plots/distance_to_goal",
            "/plots/reward", "/events"}


def entities(rrd: Path) -> set[str]:
    """Entity paths of a Rerun recording, read back with Rerun's own ``rrd print``."""
    rerun = Path(sys.executable).with_name("rerun")
    out = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    found = set()
    for word in out.stdout.split():
        word = word.strip(",:'\"()[]{}")
        if word.startswith(("/world", "/plots", "/events")):
            found.add(word)
    return found


@pytest.fixture(scope="module")
def flown(tmp_path_factory) -> tuple[Path, Path]:
    """One short lockstep episode flown with ``--viz save:`` and recorded: (run log dir,
    live recording)."""
    out = tmp_path_factory.mktemp("viz")
    live = out / "live.rrd"
    proc = subprocess.run(up_args("--episodes", "1", "--max-steps", "60", "--policy",
                                  "scripted", "--log-dir", str(out / "logs"), "--viz",
                                  f"save:{live}"),
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"viz: drawing uav1 to {live}" in proc.stdout, proc.stdout
    [run] = list((out / "logs").glob("run-*"))
    return run, live


def test_targets_parse_or_name_the_flag():
    assert parse_target("web").kind == "web" and parse_target("spawn").kind == "spawn"
    t = parse_target("save:out/run.rrd")
    assert t.kind == "save" and t.path == Path("out/run.rrd")
    for bad in ("save:", "save:x.mcap", "browser", ""):
        with pytest.raises(ValueError, match="--viz"):
            parse_target(bad)


def test_fan_triangles_give_each_face_its_triangles():
    """The icosahedron's faces as the view fills them (bus.ros.view, shared with the
    log's 3D view)."""
    from perception.icosahedron import TruncatedIcosahedron

    ico = TruncatedIcosahedron(4.0)
    tris, owner = fan_triangles(ico.faces)
    # 12 pentagons of 3 triangles, 20 hexagons of 4
    assert tris.shape == (12 * 3 + 20 * 4, 3)
    assert np.bincount(owner).tolist() == [3] * 12 + [4] * 20
    centroid = ico.vertices[tris].mean(axis=1)  # every triangle lies on its face's plane
    assert np.allclose(np.einsum("ij,ij->i", centroid, ico.normals[owner]),
                       ico.offsets[owner], atol=1e-4)
    c = face_colours(np.array([0.0, 0.5, 1.0]))
    assert c[0, 3] == 0.0 < c[1, 3] and c[1, 1] > c[2, 1]  # free unseen, nearer redder


def test_the_first_scan_is_drawn_then_one_every_scan_every_steps():
    """A short or loaded live run still shows a scan (the CI run of 507ca1e drew none:
    each step's scan came while the feed was behind, and only multiples of
    ``scan_every`` were drawn)."""
    import rerun as rr

    from skyloop.viewer import RunView

    view = RunView(rr.RecordingStream("skyloop-test"), scan_every=5)
    drawn = []
    for step in range(3, 40):
        view.step = step
        if view.wants_scan(behind=step < 20):
            drawn.append(step)
            view._scan_step = step  # what drawing the scan records
    assert drawn == [3, 20, 25, 30, 35]  # the first, one while behind, then every 5th


def test_bad_logs_get_one_line_errors(tmp_path):
    (tmp_path / "random.mcap").write_bytes(np.random.default_rng(0).bytes(4096))
    (tmp_path / "empty").mkdir()
    for path, says in ((tmp_path / "missing", "no such log"),
                       (tmp_path / "random.mcap", "no readable message"),
                       (tmp_path / "empty", "no .mcap file")):
        proc = subprocess.run(SKYLOOP + ["view", str(path), "--viz",
                                         f"save:{tmp_path / 'x.rrd'}"],
                              cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and says in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr and not (tmp_path / "x.rrd").exists()


def test_up_viz_draws_the_run_live(flown):
    _, live = flown
    assert ENTITIES <= entities(live)


def test_view_draws_a_log(flown, tmp_path):
    run, _ = flown
    rrd = tmp_path / "log.rrd"
    proc = subprocess.run(SKYLOOP + ["view", str(run), "--viz", f"save:{rrd}",
                                     "--scan-every", "10"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ENTITIES <= entities(rrd)
    scans = int(proc.stdout.split(" scans drawn")[0].rsplit(", ", 1)[1])
    assert scans >= 1, proc.stdout  # every 10th step of the episode


# ---------------------------------------------------------------- a real browser
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def terrain_share(png: Path) -> float:
    """Share of the 3D view (the left three quarters of the page, below the top bar) in
    the terrain's colours: green valleys to tan slopes (the viewer's
    bus.ros.view.terrain_colours), not the viewer's white, grey or blue."""
    import matplotlib.image as mpimg

    img = (mpimg.imread(png)[..., :3] * 255).astype(int)
    h, w = img.shape[:2]
    view = img[int(0.08 * h):int(0.95 * h), : int(0.72 * w)]
    r, g, b = view[..., 0], view[..., 1], view[..., 2]
    greenish = (g > b + 25) & (g >= r - 10)
    earthy = (r > b + 25) & (g > b + 10) & (r < 230)
    return float((greenish | earthy).mean())


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: apt-get install chromium "
                                             "(.ci/run does)")
def test_the_web_viewer_draws_the_scene_in_a_browser(flown, tmp_path):
    """``skyloop view --viz web`` served to headless Chromium (SwiftShader WebGL, driven
    with Playwright): the 3D view draws the world (the terrain covers much of it), not a
    blank canvas or the welcome page."""
    sync_playwright = pytest.importorskip(
        "playwright.sync_api", reason="pip install playwright (the test extra)").sync_playwright
    run, _ = flown
    web, grpc = free_port(), free_port()
    server = subprocess.Popen(SKYLOOP + ["view", str(run), "--viz", "web", "--web-port",
                                         str(web), "--grpc-port", str(grpc)],
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    try:
        assert server.stdout is not None
        url = next((line.split()[1] for line in server.stdout if line.startswith("open ")),
                   None)
        assert url is not None and url.startswith(f"http://127.0.0.1:{web}/"), url
        shot, share = tmp_path / "viewer.png", 0.0
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=CHROMIUM, headless=True,
                args=["--no-sandbox", "--enable-unsafe-swiftshader", "--use-gl=angle",
                      "--use-angle=swiftshader", "--ignore-gpu-blocklist"])
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(url)
                deadline = time.monotonic() + 180.0  # software WebGL: 20-60 s to draw
                while share < 0.3 and time.monotonic() < deadline:
                    time.sleep(3.0)
                    page.screenshot(path=str(shot), timeout=60_000)
                    share = terrain_share(shot)
            finally:
                browser.close()
        assert share >= 0.3, f"the 3D view shows {share:.0%} terrain; see {shot}"
    finally:
        server.terminate()
        server.wait(10)
