"""EGM: our schema matches the facts and the wire format, and both ends survive bad traffic."""

import socket
import struct
import time

import numpy as np
import pytest

from hardware.egm.client import RESTART_GAP_S, EgmArmLink
from hardware.egm.protocol import (
    MAX_DATAGRAM_BYTES,
    EgmHeader,
    EgmMessageError,
    EgmRobot,
    EgmSensor,
    chain_to_egm,
    egm_to_chain,
    get_joints,
    message_class,
    read_proto,
    seq_newer,
    set_joints,
)
from hardware.egm.sim import SimEgmArm
from hardware.stamped import wait_for

LIMITS = np.tile([-0.15, 0.15], (7, 1))


def _numbers(name: str) -> dict[str, int]:
    return {f.name: f.number for f in message_class(name).DESCRIPTOR.fields}


def test_schema_field_numbers_follow_the_facts() -> None:
    assert _numbers("EgmRobot") == {
        "header": 1,
        "feedBack": 2,
        "planned": 3,
        "motorState": 4,
        "mciState": 5,
        "mciConvergenceMet": 6,
        "rapidExecState": 8,
        "measuredForce": 9,
        "utilizationRate": 10,
        "moveIndex": 11,
    }
    assert _numbers("EgmSensor") == {"header": 1, "planned": 2, "speedRef": 3}
    assert _numbers("EgmHeader") == {"seqno": 1, "tm": 2, "mtype": 3}
    assert (
        _numbers("EgmFeedBack")
        == _numbers("EgmPlanned")
        == {"joints": 1, "cartesian": 2, "externalJoints": 3, "time": 4}
    )
    assert _numbers("EgmMeasuredForce") == {"fcActive": 1, "force": 2}
    assert _numbers("EgmQuaternion") == {"u0": 1, "u1": 2, "u2": 3, "u3": 4}
    mtype = EgmHeader.DESCRIPTOR.fields_by_name["mtype"].enum_type
    assert {v.name: v.number for v in mtype.values} == {
        "MSGTYPE_UNDEFINED": 0,
        "MSGTYPE_COMMAND": 1,
        "MSGTYPE_DATA": 2,
        "MSGTYPE_CORRECTION": 3,
        "MSGTYPE_PATH_CORRECTION": 4,
    }
    mci = message_class("EgmMCIState").DESCRIPTOR.enum_types_by_name["MCIStateType"]
    assert [v.number for v in mci.values] == [0, 1, 2, 3]


def test_wire_bytes_match_hand_encoding() -> None:
    header = EgmHeader(seqno=1, tm=2, mtype=EgmHeader.MSGTYPE_DATA)
    assert header.SerializeToString() == bytes([0x08, 0x01, 0x10, 0x02, 0x18, 0x02])
    msg = EgmSensor()
    msg.planned.joints.joints.append(1.0)
    joints = b"\x09" + struct.pack("<d", 1.0)  # field 1, fixed64, unpacked repeated double (proto2)
    planned = b"\x0a" + bytes([len(joints)]) + joints  # field 1 (joints), length-delimited
    assert msg.SerializeToString() == b"\x12" + bytes([len(planned)]) + planned  # field 2 (planned)


def test_schema_reader_refuses_what_it_does_not_know() -> None:
    with pytest.raises(SyntaxError, match="proto2"):
        read_proto('syntax = "proto3";')
    with pytest.raises(SyntaxError, match="';'"):
        read_proto("message A { optional double x = 1 }")
    with pytest.raises(SyntaxError):
        read_proto("service S {}")


def test_joint_conversion_puts_axis_7_in_external_joints() -> None:
    q = np.radians([10.0, 20.0, 70.0, 30.0, 40.0, 50.0, 60.0])  # chain order 1-2-7-3-4-5-6
    joints, external = chain_to_egm(q)
    assert joints == pytest.approx([10, 20, 30, 40, 50, 60])
    assert external == pytest.approx([70])
    np.testing.assert_allclose(egm_to_chain(joints, external), q)
    with pytest.raises(EgmMessageError):
        egm_to_chain(joints[:5], external)
    with pytest.raises(EgmMessageError):
        egm_to_chain(joints, [])
    with pytest.raises(EgmMessageError):
        egm_to_chain([float("nan")] * 6, [0.0])


def test_sequence_numbers_wrap_around() -> None:
    assert seq_newer(0, 0xFFFFFFFF) == 1
    assert seq_newer(7, 7) == 0
    assert seq_newer(3, 5) == -2


def _pair(link_speed: float, arm_speed: float):
    link = EgmArmLink("left", "127.0.0.1", 0, np.full(7, link_speed), robot=("127.0.0.1", 0))
    arm = SimEgmArm("left", ("127.0.0.1", link.port), np.zeros(7), LIMITS, np.full(7, arm_speed))
    arm.start_streaming()
    link.state.wait(1.0)
    return link, arm


def _track(arm: SimEgmArm, goal: np.ndarray, timeout_s: float) -> list[tuple[float, np.ndarray]]:
    trace = [(time.monotonic(), arm.joints)]
    while np.max(np.abs(trace[-1][1] - goal)) > 1e-9 and time.monotonic() - trace[0][0] < timeout_s:
        time.sleep(0.01)
        trace.append((time.monotonic(), arm.joints))
    return trace


def _max_speed(trace: list[tuple[float, np.ndarray]], window_s: float = 0.05) -> float:
    """Fastest joint speed (rad/s) over any span of at least `window_s` (shorter ones are scheduling noise)."""
    return max(np.max(np.abs(q1 - q0)) / (t1 - t0) for t0, q0 in trace for t1, q1 in trace if t1 - t0 >= window_s)


@pytest.mark.parametrize(("link_speed", "arm_speed"), [(100.0, 1.0), (0.5, 100.0)])
def test_arm_follows_within_speed_and_position_limits(link_speed: float, arm_speed: float) -> None:
    """The slower of the link's setpoint speed and the robot's velocity limit bounds the motion."""
    link, arm = _pair(link_speed, arm_speed)
    try:
        goal = np.array([0.1, -0.1, 0.05, 0.0, 0.1, 0.0, -0.05])
        link.set_goal(goal)
        trace = _track(arm, goal, 2.0)
        np.testing.assert_allclose(trace[-1][1], goal, atol=1e-9)
        speed = min(link_speed, arm_speed)
        assert _max_speed(trace) <= speed * 1.2
        assert trace[-1][0] - trace[0][0] >= 0.1 / speed * 0.8
        link.set_goal(np.full(7, 0.5))  # beyond the robot's limits: it stops at them
        trace = _track(arm, np.full(7, 0.15), 3.0)
        np.testing.assert_allclose(trace[-1][1], 0.15)
    finally:
        link.close()
        arm.close()


def _robot_msg(seq: int, q: np.ndarray | None = None) -> bytes:
    msg = EgmRobot()
    msg.header.seqno = seq
    if q is not None:
        set_joints(msg.feedBack, q)
    return msg.SerializeToString()


def test_link_answers_only_valid_new_messages() -> None:
    robot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    robot.bind(("127.0.0.1", 0))
    link = EgmArmLink("right", "127.0.0.1", 0, np.full(7, 1.0), robot=robot.getsockname())
    q = np.full(7, 0.1)

    def answered(data: bytes) -> EgmSensor:
        robot.sendto(data, ("127.0.0.1", link.port))
        robot.settimeout(1.0)
        reply = EgmSensor()
        reply.ParseFromString(robot.recv(4096))
        return reply

    def ignored(data: bytes, counter: str, count: int) -> bool:
        robot.sendto(data, ("127.0.0.1", link.port))
        assert wait_for(lambda: link.stats[counter] == count, 10.0)
        robot.settimeout(0.02)
        with pytest.raises(TimeoutError):
            robot.recv(4096)
        return True

    try:
        assert ignored(b"\xff\x00garbage\x13", "malformed", 1)
        assert ignored(_robot_msg(1, q)[:-5], "malformed", 2)  # truncated
        assert ignored(b"\x08" * (MAX_DATAGRAM_BYTES + 100), "malformed", 3)  # oversized
        assert ignored(_robot_msg(1), "malformed", 4)  # no joints
        first = answered(_robot_msg(10, q))
        assert first.header.mtype == EgmHeader.MSGTYPE_CORRECTION
        np.testing.assert_allclose(get_joints(first.planned), q)  # holds the robot where it is
        assert ignored(_robot_msg(10, q), "out_of_order", 1)  # repeated
        assert ignored(_robot_msg(8, q), "out_of_order", 2)  # old
        assert answered(_robot_msg(13, q)).header.seqno == 2  # 11 and 12 lost
        answered(_robot_msg(5000, q))
        answered(_robot_msg(2, q))  # far behind: EGM restarted on the controller
        time.sleep(RESTART_GAP_S + 0.05)
        answered(_robot_msg(1, q))  # behind after a pause: restarted again
        assert link.stats["lost"] == 2 + 4986
        assert link.stats["restarts"] == 2
        assert wait_for(lambda: link.stats["replied"] == 5, 10.0)  # counted just after the send
    finally:
        robot.close()
        link.close()


def test_sim_arm_ignores_bad_replies() -> None:
    sensor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sensor.bind(("127.0.0.1", 0))
    sensor.settimeout(1.0)
    arm = SimEgmArm("left", sensor.getsockname(), np.zeros(7), LIMITS, np.full(7, 10.0))
    arm.start_streaming()

    def reply(data: bytes) -> None:
        _, robot_addr = sensor.recvfrom(4096)
        sensor.sendto(data, robot_addr)

    def sensor_msg(seq: int, q: np.ndarray) -> bytes:
        msg = EgmSensor()
        msg.header.seqno = seq
        set_joints(msg.planned, q)
        return msg.SerializeToString()

    try:
        reply(b"\x00\x01\x02 not protobuf")
        reply(EgmSensor().SerializeToString())  # no joints
        reply(sensor_msg(5, np.full(7, 0.01)))
        assert wait_for(lambda: arm.stats["accepted"] == 1, 10.0)
        reply(sensor_msg(5, np.full(7, 0.2)))  # repeated sequence number: ignored
        assert wait_for(lambda: arm.stats["out_of_order"] == 1, 10.0)
        assert wait_for(lambda: np.allclose(arm.joints, 0.01), 10.0)
        assert arm.stats["malformed"] == 2
    finally:
        arm.close()
        sensor.close()
