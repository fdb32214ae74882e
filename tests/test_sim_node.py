"""The simulator service end to end: clock, ground truth, teleport and obstacle queries, the IMU's pty."""

from __future__ import annotations

import asyncio
import math

import pytest
import serial

from proto.messages import Clock, GroundTruth, ObstacleRequest, Pose2D, TeleportRequest
from services.common.query import query
from tests.support.waiting import wait_for

pytestmark = pytest.mark.integration


async def test_sim_service_clock_truth_queries_and_imu(stack_factory, tmp_path) -> None:
    imu_link = tmp_path / "imu"
    stack = stack_factory(services=["sim"], speed=4.0, world="empty_room",
                          extra_args=["--set", f'sim.imu_link="{imu_link}"']).start()
    session = stack.session()
    clocks: list[Clock] = []
    truth: list[GroundTruth] = []
    from proto import codec

    subs = [session.declare_subscriber(stack.keys("clock"),
                                       lambda s: clocks.append(codec.decode_as(Clock, s.payload.to_bytes()))),
            session.declare_subscriber(stack.keys("sim/ground_truth"),
                                       lambda s: truth.append(codec.decode_as(GroundTruth, s.payload.to_bytes())))]
    try:
        await wait_for(lambda: len(clocks) > 150 and len(truth) > 30, timeout_s=20)
        stamps = [c.stamp for c in clocks[-100:]]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))
        assert [round(b - a, 6) for a, b in zip(stamps, stamps[1:])] == [0.01] * 99
        await wait_for(lambda: clocks[-1].speed_factor > 2.0, timeout_s=10, message="speed factor never measured")
        assert truth[-1].pose == Pose2D(x=0.0, y=0.0, theta=0.0) and not truth[-1].collided

        reply = await query(session, stack.keys, "sim/teleport", TeleportRequest(pose=Pose2D(x=2.0, y=-1.0, theta=1.0)))
        assert reply.ok
        await wait_for(lambda: truth[-1].pose.x == 2.0 and truth[-1].pose.theta == 1.0, timeout_s=5)
        bad = await query(session, stack.keys, "sim/teleport", TeleportRequest(pose=Pose2D(x=math.nan)))
        assert not bad.ok and "finite" in bad.message

        add = await query(session, stack.keys, "sim/obstacles", ObstacleRequest(action="add", id="crate"))
        assert add.ok and add.ids == ["crate"]
        add = await query(session, stack.keys, "sim/obstacles",
                          ObstacleRequest(action="add", id="wall", rect=[3.5, -2.0, 4.0, 2.0]))
        assert add.ids == ["crate", "wall"]
        missing = await query(session, stack.keys, "sim/obstacles", ObstacleRequest(action="remove", id="nope"))
        assert not missing.ok and "nope" in missing.message
        cleared = await query(session, stack.keys, "sim/obstacles", ObstacleRequest(action="clear"))
        assert cleared.ok and cleared.ids == []

        # the Razor IMU on its pty: the drive service would open it like this
        with serial.Serial(str(imu_link), 57600, timeout=2.0) as port:
            port.reset_input_buffer()
            port.readline()  # may start mid-line
            line = port.readline()
            assert line.startswith(b"#YPR=") and line.endswith(b"\r\n")
            yaw = float(line[5:-2].split(b",")[0])
            assert yaw == pytest.approx(-math.degrees(1.0), abs=1.0)  # teleported heading, clockwise degrees
            port.write(b"#s12")
            await asyncio.sleep(0)
            for _ in range(20):
                if port.readline() == b"#SYNCH12\r\n":
                    break
            else:
                pytest.fail("no #SYNCH reply")
    finally:
        for s in subs:
            s.undeclare()
