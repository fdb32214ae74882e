"""Synchronous mapping (``mapping_sync``, a replayed log): every scan reaches the mapper, placed with the odometry at
its stamp, in whatever order the scan and odom topics reach the event loop (Zenoh hands each topic over from its
own thread, so under load a scan may overtake its odometry by several messages)."""

from __future__ import annotations

import asyncio
import math

import numpy as np

from proto import Keys
from proto.messages import LaserScan, Odometry, Pose2D
from services.common.node import Node
from services.common.robot import RobotSpec
from services.common.service import ServiceContext
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.localization.config import LocalizationConfig
from services.localization.mapping import MappingNode
from services.localization.node import Outputs
from tests.support.waiting import wait_for

#: a lidar at 5 Hz, odometry at 10 Hz, the robot driving at 0.3 m/s along x in a 6 x 4 m room
SCAN_PERIOD_S, ODOM_PERIOD_S, SPEED_M_S = 0.2, 0.1, 0.3


def _room_scan(stamp: float, x_m: float) -> LaserScan:
    """A 360-beam scan from (x_m, 0, 0) inside the rectangle [-3, 3] x [-2, 2]: range to the nearest wall."""
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (3.0 - x_m) / c, np.where(c < 0, (-3.0 - x_m) / c, np.inf))
        ty = np.where(s > 0, 2.0 / s, np.where(s < 0, -2.0 / s, np.inf))
    ranges = np.minimum(tx, ty).astype("<f4")
    return LaserScan(stamp=stamp, angle_min=-math.pi, angle_max=float(angles[-1]),
                     angle_increment=float(angles[1] - angles[0]), range_min=0.05, range_max=20.0,
                     ranges=ranges.tobytes())


def _messages(duration_s: float) -> tuple[list[LaserScan], list[Odometry]]:
    scans = [_room_scan(float(t), -1.0 + SPEED_M_S * float(t)) for t in np.arange(0.0, duration_s, SCAN_PERIOD_S)]
    odom = [Odometry(stamp=float(t), pose=Pose2D(x=-1.0 + SPEED_M_S * float(t)))
            for t in np.arange(0.0, duration_s + 1.0, ODOM_PERIOD_S)]
    return scans, odom


async def test_every_scan_is_mapped_when_scans_overtake_their_odometry(router):
    """Each scan reaches the loop 0.6 s of odometry ahead of the odom that covers its stamp (three scans ahead):
    all of them are still placed and mapped, none dropped for want of odometry."""
    session = open_session(ZenohSettings(connect=[router]))
    node = Node("localization", session, Keys("sync1"))
    cfg = LocalizationConfig(mode="mapping", mapping_sync=True, mapping_min_travel_m=0.0, mapping_min_turn_rad=0.0)
    ctx = ServiceContext(node=node, robot=RobotSpec(), config={"localization": cfg}, config_path=None)
    mapping = MappingNode(ctx, cfg, Outputs.declare(node), (0.0, 0.0, 0.0))
    scans, odom = _messages(6.0)
    lag_s = 0.6
    arrivals = sorted([(s.stamp - lag_s, 0, s) for s in scans] + [(o.stamp, 1, o) for o in odom],
                      key=lambda a: (a[0], a[1]))
    for _, _, msg in arrivals:
        (mapping.on_scan if isinstance(msg, LaserScan) else mapping.on_odom)(msg)
    await wait_for(lambda: not mapping._drain_scheduled, timeout_s=60.0, message="the synchronous backlog drained")
    assert mapping.stats["processed"] == len(scans), f"{len(scans)} scans; stats {mapping.stats}"
    assert mapping.stats.get("scans_out_of_odom_history", 0) == 0
    assert mapping.stats["scans"] == len(scans)
    pose = mapping.mapper.pose
    assert pose is not None and abs(pose[0] - SPEED_M_S * scans[-1].stamp) < 0.1  # placed with its odometry
    node.close()
    session.close()
    await asyncio.sleep(0)
