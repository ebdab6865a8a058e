"""Mission, geofence and rally lists over the MAVLink mission protocol, real UDP.

A pymavlink ground station (tests/gcs_rig.py) uploads and downloads item by item, the
way QGroundControl does; upload retries and timeouts run on the simulated clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_rig import DT, GcsRig, mavutil, of_type
from pymavlink.dialects.v20 import common as M

from mavlink_bridge import frames
from mavlink_bridge.gcs.missions import MissionItem

ORIGIN = (47.397742, 8.545594, 488.0)
LAT0, LON0 = ORIGIN[0], ORIGIN[1]
MISSION, FENCE, RALLY = 0, 1, 2


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[GcsRig]:
    r = GcsRig(tmp_path / "p.json")
    r.got: list[tuple[int, list[MissionItem]]] = []  # type: ignore[attr-defined]
    r.link.missions.on_mission = lambda t, items: r.got.append((t, items))  # type: ignore
    yield r
    r.close()


def item(seq: int, command: int, lat: float, lon: float, alt: float, *, mission_type: int = 0,
         frame: int = M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, p1: float = 0.0) -> Any:
    return M.MAVLink_mission_item_int_message(1, 1, seq, frame, command, 0, 1, p1, 0.0, 0.0,
                                              math.nan, round(lat * 1e7), round(lon * 1e7),
                                              alt, mission_type)


def upload(rig: GcsRig, items: list[Any], mission_type: int, count: int | None = None) -> Any:
    """QGroundControl's upload loop: MISSION_COUNT, answer each request, until the ACK."""
    got = rig.exchange(M.MAVLink_mission_count_message(
        1, 1, len(items) if count is None else count, mission_type))
    for _ in range(len(items) + 2):
        acks = of_type(got, "MISSION_ACK")
        if acks:
            assert len(acks) == 1 and acks[0].mission_type == mission_type
            assert (acks[0].target_system, acks[0].target_component) == (255, 190)
            return acks[0]
        (req,) = of_type(got, "MISSION_REQUEST_INT")
        assert req.mission_type == mission_type and (req.target_system, req.target_component) \
            == (255, 190)
        got = rig.exchange(items[req.seq])
    raise AssertionError("no MISSION_ACK")


def download(rig: GcsRig, mission_type: int) -> list[Any]:
    (count,) = of_type(rig.exchange(M.MAVLink_mission_request_list_message(
        1, 1, mission_type)), "MISSION_COUNT")
    assert count.mission_type == mission_type
    out = []
    for seq in range(count.count):
        (it,) = of_type(rig.exchange(M.MAVLink_mission_request_int_message(
            1, 1, seq, mission_type)), "MISSION_ITEM_INT")
        assert it.seq == seq and it.mission_type == mission_type
        out.append(it)
    rig.exchange(M.MAVLink_mission_ack_message(1, 1, M.MAV_MISSION_ACCEPTED, mission_type))
    return out


def fields(m: Any) -> tuple:
    return (m.seq, m.frame, m.command, m.x, m.y, m.z, m.param1, m.mission_type)


NORTH_10M = math.degrees(10.0 / frames.EARTH_RADIUS_M)
EAST_20M = math.degrees(20.0 / (frames.EARTH_RADIUS_M * math.cos(math.radians(LAT0))))


def test_connect_lists_are_empty_for_every_type(rig: GcsRig) -> None:
    for t in (MISSION, FENCE, RALLY):
        assert download(rig, t) == []
    assert rig.link.counters["mission.download"] == 3
    assert rig.link.counters["mission.download_acked"] == 3
    got = rig.exchange(M.MAVLink_mission_request_list_message(1, 1, 7))
    assert of_type(got, "MISSION_ACK")[0].type == M.MAV_MISSION_UNSUPPORTED


def test_mission_upload_download_and_local_goals(rig: GcsRig) -> None:
    items = [item(0, M.MAV_CMD_NAV_TAKEOFF, LAT0, LON0, 5.0),
             item(1, M.MAV_CMD_NAV_WAYPOINT, LAT0 + NORTH_10M, LON0 + EAST_20M, 6.0),
             item(2, M.MAV_CMD_DO_CHANGE_SPEED, 0, 0, 0, frame=M.MAV_FRAME_MISSION, p1=1.0),
             item(3, M.MAV_CMD_NAV_WAYPOINT, LAT0, LON0, 500.0, frame=M.MAV_FRAME_GLOBAL_INT),
             item(4, M.MAV_CMD_NAV_LAND, 0, 0, 0)]
    assert upload(rig, items, MISSION).type == M.MAV_MISSION_ACCEPTED
    assert [t for t, _ in rig.got] == [MISSION]
    accepted = rig.got[0][1]
    assert [i.command for i in accepted] == [22, 16, 178, 16, 21]
    assert accepted[1].lat_lon_alt == pytest.approx((LAT0 + NORTH_10M, LON0 + EAST_20M, 6.0))
    goal = accepted[1].local_position(ORIGIN, home=(0.0, 0.0, 1.0))
    assert goal == pytest.approx((20.0, 10.0, 7.0), abs=0.02)  # degE7 is ~1 cm
    assert accepted[3].local_position(ORIGIN) == pytest.approx((0.0, 0.0, 12.0), abs=1e-3)
    assert accepted[2].local_position(ORIGIN) is None
    down = download(rig, MISSION)
    assert [fields(m) for m in down] == [fields(m) for m in items]
    assert [m.current for m in down] == [1, 0, 0, 0, 0]
    # The legacy MISSION_REQUEST gets the float MISSION_ITEM (degrees), as from PX4.
    (legacy,) = of_type(rig.exchange(M.MAVLink_mission_request_message(1, 1, 1, MISSION)),
                        "MISSION_ITEM")
    assert (legacy.x, legacy.y) == pytest.approx((LAT0 + NORTH_10M, LON0 + EAST_20M), abs=1e-6)
    # Out of range: INVALID_SEQUENCE.
    got = rig.exchange(M.MAVLink_mission_request_int_message(1, 1, 5, MISSION))
    assert of_type(got, "MISSION_ACK")[0].type == M.MAV_MISSION_INVALID_SEQUENCE


def test_fence_and_rally_with_local_frames_then_empty_upload_clears(rig: GcsRig) -> None:
    fence = [item(i, M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, LAT0 + dy * NORTH_10M,
                  LON0 + dx * EAST_20M, 0.0, mission_type=FENCE, p1=4.0,
                  frame=M.MAV_FRAME_GLOBAL_INT)
             for i, (dx, dy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1)))]
    fence.append(item(4, M.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, LAT0, LON0, 0.0,
                      mission_type=FENCE, p1=3.0, frame=M.MAV_FRAME_GLOBAL_INT))
    rally = [item(0, M.MAV_CMD_NAV_RALLY_POINT, LAT0, LON0 + EAST_20M, 10.0, mission_type=RALLY),
             M.MAVLink_mission_item_int_message(1, 1, 1, M.MAV_FRAME_LOCAL_NED,
                                                M.MAV_CMD_NAV_RALLY_POINT, 0, 1, 0, 0, 0, 0,
                                                50000, -30000, -4.0, RALLY)]  # N 5 m, E -3 m
    assert upload(rig, fence, FENCE).type == M.MAV_MISSION_ACCEPTED
    assert upload(rig, rally, RALLY).type == M.MAV_MISSION_ACCEPTED
    assert [fields(m) for m in download(rig, FENCE)] == [fields(m) for m in fence]
    assert [fields(m) for m in download(rig, RALLY)] == [fields(m) for m in rally]
    assert download(rig, MISSION) == []  # lists are separate
    assert rig.got[1][1][1].local_position(ORIGIN) == pytest.approx((-3.0, 5.0, 4.0))
    assert rig.got[1][1][0].local_position(ORIGIN) == pytest.approx((20.0, 0.0, 10.0), abs=0.02)
    # An empty upload is valid and clears; CLEAR_ALL for every type clears the rest.
    assert upload(rig, [], RALLY).type == M.MAV_MISSION_ACCEPTED
    assert rig.got[-1] == (RALLY, []) and download(rig, RALLY) == []
    ack = of_type(rig.exchange(M.MAVLink_mission_clear_all_message(1, 1, 255)), "MISSION_ACK")
    assert [(a.type, a.mission_type) for a in ack] == [(M.MAV_MISSION_ACCEPTED, 255)]
    assert download(rig, FENCE) == [] and [t for t, i in rig.got[-3:] if not i] == [0, 1, 2]


BAD_UPLOADS = [  # (what, first item sent, expected MAV_MISSION result)
    ("sequence ahead", item(1, 16, LAT0, LON0, 5.0), M.MAV_MISSION_INVALID_SEQUENCE),
    ("rally command in a mission", item(0, M.MAV_CMD_NAV_RALLY_POINT, LAT0, LON0, 5.0),
     M.MAV_MISSION_UNSUPPORTED),
    ("unknown command", item(0, 31000, LAT0, LON0, 5.0), M.MAV_MISSION_UNSUPPORTED),
    ("terrain frame", item(0, 16, LAT0, LON0, 5.0, frame=M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT),
     M.MAV_MISSION_UNSUPPORTED_FRAME),
    ("waypoint in MISSION frame", item(0, 16, LAT0, LON0, 5.0, frame=M.MAV_FRAME_MISSION),
     M.MAV_MISSION_UNSUPPORTED_FRAME),
    ("NaN altitude", item(0, 16, LAT0, LON0, math.nan), M.MAV_MISSION_INVALID_PARAM7),
    ("latitude out of range", item(0, 16, 91.0, LON0, 5.0), M.MAV_MISSION_INVALID_PARAM5_X),
    ("longitude out of range", item(0, 16, LAT0, 181.0, 5.0), M.MAV_MISSION_INVALID_PARAM6_Y),
    ("NaN latitude (float MISSION_ITEM)", M.MAVLink_mission_item_message(
        1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT, 16, 0, 1, 0, 0, 0, 0, math.nan, LON0, 5.0, 0),
     M.MAV_MISSION_INVALID_PARAM5_X),
    ("item of another list type", item(0, 16, LAT0, LON0, 5.0, mission_type=FENCE),
     M.MAV_MISSION_ERROR),
]


def test_failing_uploads_are_refused_with_the_right_error_and_keep_the_old_list(
        rig: GcsRig) -> None:
    good = [item(0, 16, LAT0, LON0, 5.0), item(1, 16, LAT0 + NORTH_10M, LON0, 5.0)]
    assert upload(rig, good, MISSION).type == M.MAV_MISSION_ACCEPTED
    for what, first, result in BAD_UPLOADS:
        rig.exchange(M.MAVLink_mission_count_message(1, 1, 2, MISSION))
        acks = of_type(rig.exchange(first), "MISSION_ACK")
        assert [a.type for a in acks] == [result], what
        assert [fields(m) for m in download(rig, MISSION)] == [fields(m) for m in good], what
    bad_polygon = [item(0, M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, LAT0, LON0, 0.0,
                        mission_type=FENCE, p1=2.0)]
    assert upload(rig, bad_polygon, FENCE).type == M.MAV_MISSION_INVALID_PARAM1
    assert upload(rig, [], MISSION, count=60000).type == M.MAV_MISSION_NO_SPACE
    c = rig.link.counters
    assert c["mission.upload_failed"] == len(BAD_UPLOADS) + 1
    assert c[f"mission.refused.{M.MAV_MISSION_INVALID_SEQUENCE}"] == 1
    assert len(rig.got) == 1 and c["handler_error"] == 0
    # An item nobody asked for is ignored and counted.
    assert not rig.exchange(item(0, 16, LAT0, LON0, 5.0))
    assert c["mission.item_unexpected"] == 0 and rig.link.counters["mission.item_unexpected"] == 1


def test_unanswered_upload_is_retried_on_simulated_time_then_cancelled(rig: GcsRig) -> None:
    rig.exchange(M.MAVLink_mission_count_message(1, 1, 2, MISSION))
    # Nobody answers: the request is re-sent every 0.25 s of vehicle time, 10 times.
    got = rig.exchange(ticks=int(round(3.0 / DT)))
    requests = of_type(got, "MISSION_REQUEST_INT")
    assert len(requests) == 10 and {r.seq for r in requests} == {0}
    acks = of_type(got, "MISSION_ACK")
    assert [a.type for a in acks] == [M.MAV_MISSION_OPERATION_CANCELLED]
    assert any("timed out" in s.text for s in of_type(got, "STATUSTEXT"))
    assert rig.link.counters["mission.upload_timeout"] == 1
    # A late answer after a re-send still completes an upload that is alive.
    rig.exchange(M.MAVLink_mission_count_message(1, 1, 1, RALLY))
    got = rig.exchange(ticks=int(round(0.3 / DT)))
    assert [r.seq for r in of_type(got, "MISSION_REQUEST_INT")] == [0]
    acks = of_type(rig.exchange(item(0, M.MAV_CMD_NAV_RALLY_POINT, LAT0, LON0, 5.0,
                                     mission_type=RALLY)), "MISSION_ACK")
    assert [a.type for a in acks] == [M.MAV_MISSION_ACCEPTED]


def test_second_ground_station_is_denied_while_one_uploads(rig: GcsRig) -> None:
    other = mavutil.mavlink_connection(f"udpout:127.0.0.1:{rig.link.address('gcs')[1]}",
                                       source_system=254, source_component=190)
    try:
        rig.exchange(M.MAVLink_mission_count_message(1, 1, 1, MISSION))
        other.mav.send(M.MAVLink_mission_count_message(1, 1, 3, MISSION))
        rig.tick()
        ack = other.recv_match(type="MISSION_ACK", blocking=True, timeout=2.0)
        assert ack is not None and ack.type == M.MAV_MISSION_DENIED
        # The first upload goes on undisturbed.
        acks = of_type(rig.exchange(item(0, 16, LAT0, LON0, 5.0)), "MISSION_ACK")
        assert [a.type for a in acks] == [M.MAV_MISSION_ACCEPTED]
    finally:
        other.close()


def test_set_current_and_progress_reports(rig: GcsRig) -> None:
    items = [item(i, 16, LAT0 + i * NORTH_10M, LON0, 5.0) for i in range(3)]
    assert upload(rig, items, MISSION).type == M.MAV_MISSION_ACCEPTED
    cur = of_type(rig.exchange(M.MAVLink_mission_set_current_message(1, 1, 2)),
                  "MISSION_CURRENT")
    assert [(c.seq, c.total) for c in cur] == [(2, 3)]
    got = rig.exchange(M.MAVLink_mission_set_current_message(1, 1, 7))
    assert "no item 7" in of_type(got, "STATUSTEXT")[0].text
    assert rig.link.counters["mission.set_current_invalid"] == 1
    got = rig.exchange(M.MAVLink_command_long_message(
        1, 1, M.MAV_CMD_DO_SET_MISSION_CURRENT, 0, 1, 0, 0, 0, 0, 0, 0))
    assert of_type(got, "COMMAND_ACK")[0].result == M.MAV_RESULT_ACCEPTED
    assert of_type(got, "MISSION_CURRENT")[0].seq == 1
    # The node reports progress.
    rig.link.missions.mission_current(2)
    rig.link.missions.item_reached(2)
    got = rig.drain()
    assert of_type(got, "MISSION_CURRENT")[0].mission_state == M.MISSION_STATE_ACTIVE
    assert [m.seq for m in of_type(got, "MISSION_ITEM_REACHED")] == [2]
    got = rig.exchange(M.MAVLink_command_long_message(
        1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_MISSION_CURRENT, 0, 0, 0, 0, 0, 0))
    cur = of_type(got, "MISSION_CURRENT")
    assert cur[-1].seq == 2 and cur[-1].mission_state == M.MISSION_STATE_COMPLETE
