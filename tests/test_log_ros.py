"""Logs that show the flight in 3D by ROS 2 conventions (issue 12 section 1): the VLP-16
point-cloud layout, the derived log topics (TF, clock, world, goal, path, icosahedron),
a short real run read back with rosbags, and the generated ``skyloop_msgs`` package."""

from __future__ import annotations

import numpy as np
import pytest

from bus import messages as m


# ------------------------------------------------------------------ the point cloud
def test_cloud_has_the_vlp16_fields_and_perception_still_reads_xyz():
    pts = np.random.default_rng(1).normal(scale=5, size=(500, 3)).astype(np.float32)
    rings = m.elevation_rings(pts, -15.0, 15.0, 16)
    back = m.decode(m.POINTCLOUD2, m.encode(m.pointcloud(pts, 2.5, rings=rings)))
    layout = [(f.name, f.offset, f.datatype, f.count) for f in back.fields]
    # velodyne_pointcloud's ROS 2 XYZIR: float32 x y z intensity, uint16 ring, no padding
    assert layout == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1),
                      ("intensity", 12, 7, 1), ("ring", 16, 4, 1)]
    assert (back.point_step, back.row_step, back.header.frame_id) == (18, 18 * 500, "lidar")
    np.testing.assert_array_equal(m.points_from_pointcloud(back), pts)
    np.testing.assert_array_equal(m.pointcloud_field(back, "ring"), rings)
    assert (m.pointcloud_field(back, "intensity") == m.LIDAR_INTENSITY).all()
    with pytest.raises(ValueError, match="no field"):
        m.pointcloud_field(back, "time")


def test_rings_are_the_lidar_channels():
    """Each return's ring recovered from its elevation is the channel of its ray (rays
    are column-major, ``channel = ray % 16``), on a full-range forest scan."""
    from sitl.lidar import Lidar, LidarConfig
    from sitl.world import World, load_scenario

    lidar = Lidar(World(load_scenario("forest")),
                  LidarConfig(max_range=100.0, min_range=0.0, noise_sigma=0.0))
    pose = (np.array([0.0, 0.0, 3.5]), np.eye(3))
    pts = lidar.scan(*pose, 0.0)
    rays = np.flatnonzero(lidar.ranges(*pose, 0.0) < 100.0)
    assert len(pts) == len(rays) > 10_000
    cfg = lidar.config
    rings = m.elevation_rings(pts, cfg.min_elevation_deg, cfg.max_elevation_deg, cfg.channels)
    np.testing.assert_array_equal(rings, rays % 16)


# ------------------------------------------------------------------ the skyloop_msgs package
def test_ros2_package_lists_every_msg_and_dependency(tmp_path, capsys):
    """The generated interface package: every bus/msg/*.msg copied and listed in
    rosidl_generate_interfaces, every package whose types they use (read from the type
    store's field definitions, independently of the generator) a dependency in
    package.xml and CMakeLists.txt."""
    import xml.etree.ElementTree as ET

    from bus import ros2_pkg

    assert ros2_pkg.main(["--out", str(tmp_path)]) == 0
    assert "skyloop_msgs" in capsys.readouterr().out
    root = tmp_path / "skyloop_msgs"
    names = sorted(p.name for p in m.MSG_DIR.glob("*.msg"))
    assert names and sorted(p.name for p in (root / "msg").glob("*.msg")) == names
    for name in names:
        assert (root / "msg" / name).read_bytes() == (m.MSG_DIR / name).read_bytes()
    assert {f"skyloop_msgs/msg/{n[:-4]}" for n in names} == set(m.PROJECT_TYPES)

    def used(type_name: str) -> set[str]:
        out = set()
        for _, (kind, detail) in m.TYPESTORE.fielddefs[type_name][1]:
            sub = detail[0] if kind in (3, 4) else detail  # arrays, sequences: element
            if isinstance(sub, tuple) and sub[0] == 2:
                sub = sub[1]
            if isinstance(sub, str):
                out.add(sub.split("/")[0])
        return out

    expected = set().union(*(used(t) for t in m.PROJECT_TYPES)) - {"skyloop_msgs"}
    assert expected == {"builtin_interfaces", "geometry_msgs", "std_msgs"}

    pkg = ET.parse(root / "package.xml").getroot()
    assert pkg.get("format") == "3" and pkg.findtext("name") == "skyloop_msgs"
    assert {e.text for e in pkg.findall("depend")} == expected
    assert {e.text for e in pkg.findall("buildtool_depend")} == {
        "ament_cmake", "rosidl_default_generators"}
    assert pkg.findtext("exec_depend") == "rosidl_default_runtime"
    assert pkg.findtext("member_of_group") == "rosidl_interface_packages"
    assert pkg.find("export").findtext("build_type") == "ament_cmake"

    cmake = (root / "CMakeLists.txt").read_text()
    assert "project(skyloop_msgs)" in cmake
    block = cmake.split("rosidl_generate_interfaces(${PROJECT_NAME}", 1)[1].split(")", 1)[0]
    assert sorted(line.strip().strip('"') for line in block.splitlines()
                  if line.strip().startswith('"')) == [f"msg/{n}" for n in names]
    deps_line = next(line for line in block.splitlines() if "DEPENDENCIES" in line)
    assert set(deps_line.split()[1:]) == expected
    for dep in expected | {"ament_cmake", "rosidl_default_generators"}:
        assert f"find_package({dep} REQUIRED)" in cmake
    assert "ament_package()" in cmake
