"""What a ground station asks first: AUTOPILOT_VERSION, then the parameter protocol.

A pymavlink ground station on real UDP (127.0.0.1) against a VehicleLink with a real
Commander (tests/gcs_rig.py); parameters persisted to a file under tmp_path.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from gcs_rig import GcsRig, of_type
from pymavlink.dialects.v20 import common as mavlink

from bus import params as table
from mavlink_bridge.gcs.params import ParamServer, decode_value, default_params_file, encode_value

NAMES = [p.name for p in table.PARAMS]


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[GcsRig]:
    r = GcsRig(tmp_path / "params.json")
    yield r
    r.close()


def command_long(command: int, *params: float) -> object:
    p = list(params) + [0.0] * (7 - len(params))
    return mavlink.MAVLink_command_long_message(1, 1, command, 0, *p)


# ------------------------------------------------------------------ AUTOPILOT_VERSION
def test_request_message_autopilot_version_ack_first_then_capabilities(rig: GcsRig) -> None:
    got = rig.exchange(command_long(mavlink.MAV_CMD_REQUEST_MESSAGE,
                                    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
    kinds = [m.get_type() for m in got if m.get_type() in ("COMMAND_ACK", "AUTOPILOT_VERSION")]
    assert kinds == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    ack, ver = of_type(got, "COMMAND_ACK")[0], of_type(got, "AUTOPILOT_VERSION")[0]
    assert ack.command == mavlink.MAV_CMD_REQUEST_MESSAGE
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert (ack.target_system, ack.target_component) == (255, 190)
    for bit in ("MAVLINK2", "MISSION_INT", "PARAM_FLOAT", "SET_POSITION_TARGET_LOCAL_NED",
                "COMMAND_INT", "MISSION_FENCE", "MISSION_RALLY"):
        assert ver.capabilities & getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{bit}"), bit
    assert not ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_FTP  # not claimed
    assert ver.uid == 1 and ver.flight_sw_version >> 24 == 0 and ver.flight_sw_version & 0xFF == 255
    # The legacy command, and REQUEST_MESSAGE as COMMAND_INT, answer the same way.
    got = rig.exchange(command_long(mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1))
    assert of_type(got, "COMMAND_ACK")[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert of_type(got, "AUTOPILOT_VERSION")[0].capabilities == ver.capabilities
    got = rig.exchange(mavlink.MAVLink_command_int_message(
        1, 1, 0, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 0, 148.0, 0, 0, 0, 0, 0, 0))
    assert of_type(got, "COMMAND_ACK")[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert len(of_type(got, "AUTOPILOT_VERSION")) == 1


def test_request_message_unknown_or_bad_id_is_unsupported_and_counted(rig: GcsRig) -> None:
    for bad in (9999.0, 148.5, math.nan, -1.0):
        got = rig.exchange(command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, bad))
        acks = of_type(got, "COMMAND_ACK")
        assert [a.result for a in acks] == [mavlink.MAV_RESULT_UNSUPPORTED]
        assert not of_type(got, "AUTOPILOT_VERSION")
    assert rig.link.counters["request_message.unsupported"] == 4
    # A request for another system is ignored (and counted), not answered.
    got = rig.exchange(mavlink.MAVLink_command_long_message(
        7, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 148, 0, 0, 0, 0, 0, 0))
    assert not of_type(got, "COMMAND_ACK") and rig.link.counters["cmd.other_target"] == 1


# ------------------------------------------------------------------ parameters
def test_param_list_streams_every_value_with_consistent_count_and_index(rig: GcsRig) -> None:
    got = of_type(rig.exchange(mavlink.MAVLink_param_request_list_message(1, 1)), "PARAM_VALUE")
    assert [m.param_id for m in got] == NAMES
    assert [m.param_index for m in got] == list(range(len(NAMES)))
    assert {m.param_count for m in got} == {len(NAMES)}
    for m in got:
        p = table.BY_NAME[m.param_id]
        assert m.param_type == mavlink.MAV_PARAM_TYPE_REAL32
        assert m.param_value == pytest.approx(p.default, rel=1e-6)
    # Broadcast target (0, 0) is ours too; another system's request is not.
    assert len(of_type(rig.exchange(mavlink.MAVLink_param_request_list_message(0, 0)),
                       "PARAM_VALUE")) == len(NAMES)
    assert not of_type(rig.exchange(mavlink.MAVLink_param_request_list_message(2, 1)),
                       "PARAM_VALUE")
    assert rig.link.counters["param_request_list.other_target"] == 1


def test_param_read_by_name_and_index_unknown_answered_with_statustext(rig: GcsRig) -> None:
    m = of_type(rig.exchange(mavlink.MAVLink_param_request_read_message(
        1, 1, b"MPC_XY_VEL_MAX", -1)), "PARAM_VALUE")
    assert [(x.param_id, x.param_index, x.param_value) for x in m] == [
        ("MPC_XY_VEL_MAX", NAMES.index("MPC_XY_VEL_MAX"), 2.0)]
    m = of_type(rig.exchange(mavlink.MAVLink_param_request_read_message(1, 1, b"", 0)),
                "PARAM_VALUE")
    assert [x.param_id for x in m] == [NAMES[0]]
    for pid, idx in ((b"NO_SUCH_PARAM", -1), (b"", len(NAMES)), (b"", 30000)):
        got = rig.exchange(mavlink.MAVLink_param_request_read_message(1, 1, pid, idx))
        assert not of_type(got, "PARAM_VALUE")
        assert "unknown" in of_type(got, "STATUSTEXT")[0].text
    assert rig.link.counters["params.read_unknown"] == 3


def set_msg(name: str, value: float, ptype: int = mavlink.MAV_PARAM_TYPE_REAL32) -> object:
    return mavlink.MAVLink_param_set_message(1, 1, name.encode(), value, ptype)


def test_param_set_good_and_bad_persisted_across_restart(tmp_path: Path) -> None:
    path = tmp_path / "state" / "params.json"
    rig = GcsRig(path)
    changes: list[tuple[str, float]] = []
    rig.link.params.on_change = lambda n, v: changes.append((n, v))
    try:
        got = of_type(rig.exchange(set_msg("COM_OF_LOSS_T", 2.5)), "PARAM_VALUE")
        assert [(m.param_id, m.param_value) for m in got] == [("COM_OF_LOSS_T", 2.5)]
        assert changes == [("COM_OF_LOSS_T", 2.5)]
        assert json.loads(path.read_text())["params"]["COM_OF_LOSS_T"] == 2.5
        assert sorted(p.name for p in path.parent.iterdir()) == ["params.json"]  # no tmp left
        # Refusals: PARAM_VALUE with the current value + STATUSTEXT, counted, nothing stored.
        for msg, counter in ((set_msg("COM_OF_LOSS_T", 600.0), "set_invalid"),
                             (set_msg("COM_OF_LOSS_T", math.nan), "set_invalid"),
                             (set_msg("COM_OF_LOSS_T", 3.0, mavlink.MAV_PARAM_TYPE_INT32),
                              "set_wrong_type")):
            got = rig.exchange(msg)
            assert [(m.param_id, m.param_value) for m in of_type(got, "PARAM_VALUE")] == [
                ("COM_OF_LOSS_T", 2.5)]
            assert "COM_OF_LOSS_T" in of_type(got, "STATUSTEXT")[0].text
            assert rig.link.counters[f"params.{counter}"] >= 1
        got = rig.exchange(set_msg("NOT_A_PARAM", 1.0))
        assert not of_type(got, "PARAM_VALUE") and of_type(got, "STATUSTEXT")
        assert rig.link.counters["params.set_unknown"] == 1
        assert changes == [("COM_OF_LOSS_T", 2.5)]
        assert rig.link.counters["handler_error"] == 0
    finally:
        rig.close()
    rig = GcsRig(path)  # a restart of the link reads the file
    try:
        got = of_type(rig.exchange(mavlink.MAVLink_param_request_list_message(1, 1)),
                      "PARAM_VALUE")
        values = {m.param_id: m.param_value for m in got}
        assert values["COM_OF_LOSS_T"] == 2.5 and values["MPC_XY_VEL_MAX"] == 2.0
    finally:
        rig.close()


class _Ops:
    def __init__(self) -> None:
        self.texts: list[str] = []

    def broadcast(self, msg: object) -> None:
        pass

    def statustext(self, text: str, severity: str | int = "info") -> None:
        self.texts.append(text)


def test_corrupt_or_partly_bad_file_falls_back_to_defaults_counted(tmp_path: Path) -> None:
    path = tmp_path / "p.json"
    path.write_text("{ not json")
    server = ParamServer(_Ops(), path)
    assert server.values == table.defaults() and server.counters["load_error"] == 1
    path.write_text(json.dumps({"format": "skyloop-params/1", "params": {
        "COM_OF_LOSS_T": 9.0, "MPC_XY_VEL_MAX": 1e9, "GONE": 1.0, "SKY_FLIGHT_LVL": "x"}}))
    server = ParamServer(_Ops(), path)
    assert server.values["COM_OF_LOSS_T"] == 9.0
    assert server.values["MPC_XY_VEL_MAX"] == 2.0 and server.counters["load_skipped"] == 3
    path.write_text(json.dumps([1, 2]))
    assert ParamServer(_Ops(), path).counters["load_error"] == 1
    # A save that cannot be written is reported and counted, the value still applies.
    blocked = tmp_path / "file"
    blocked.write_text("")
    ops = _Ops()
    server = ParamServer(ops, blocked / "p.json")
    assert server.set("COM_OF_LOSS_T", 4.0) == 4.0
    assert server.counters["save_error"] == 1 and "save failed" in ops.texts[0]


def test_int_values_are_bytewise_and_default_path_is_xdg(monkeypatch: pytest.MonkeyPatch) -> None:
    for v in (0, 1, -7, 123456, 2**31 - 1):
        assert decode_value(mavlink.MAV_PARAM_TYPE_INT32, encode_value("int", v)) == v
    assert decode_value(mavlink.MAV_PARAM_TYPE_REAL32, encode_value("float", 2.5)) == 2.5
    monkeypatch.setenv("XDG_STATE_HOME", "/x/state")
    assert str(default_params_file(3)) == "/x/state/skyloop/params-sys3.json"
    monkeypatch.delenv("XDG_STATE_HOME")
    assert str(default_params_file(1)).endswith(".local/state/skyloop/params-sys1.json")


def test_sixteen_char_param_id_is_not_nul_terminated() -> None:
    msg = mavlink.MAVLink_param_value_message(b"ABCDEFGHIJKLMNOP", 1.0, 9, 1, 0)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    decoded = mav.decode(bytearray(msg.pack(mav)))
    assert decoded.param_id == "ABCDEFGHIJKLMNOP"
    assert all(len(p.name) <= 16 for p in table.PARAMS)
