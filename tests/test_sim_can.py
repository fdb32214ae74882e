"""The emulated RoboteQ controllers seen from a real CANopen master on the simulated bus (integration)."""

from __future__ import annotations

import math
import threading
import time

import canopen
import pytest

from proto import codec
from proto.messages import GroundTruth
from services.common.motor_units import MotorUnits
from services.sim.config import SimConfig
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

CFG = SimConfig()
UNITS = MotorUnits(wheel_radius_m=CFG.wheel_radius_m, gear_ratio=CFG.gear_ratio,
                   traction_counts_per_rev=CFG.traction_cpr, steer_counts_per_rev=CFG.steer_counts_per_rev,
                   steer_motor_counts_per_rev=CFG.steer_cpr)


class Master:
    """A test-side CANopen master: raw SDO, NMT, TPDO1 decoding per the documented mapping, RPDO1 sending."""

    def __init__(self, channel: str) -> None:
        self.net = canopen.Network()
        self.net.connect(interface="remote", channel=channel)
        self.nodes = {n: self.net.add_node(canopen.RemoteNode(n, canopen.ObjectDictionary())) for n in (1, 2)}
        for node in self.nodes.values():
            node.sdo.RESPONSE_TIMEOUT = 2.0
        self.counts: dict[int, tuple[int, int]] = {}
        self.tpdo1_frames = 0
        self._lock = threading.Lock()
        for n in (1, 2):
            self.net.subscribe(0x180 + n, self._on_tpdo1)

    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self.counts[can_id - 0x180] = (int.from_bytes(data[0:4], "little", signed=True),
                                           int.from_bytes(data[4:8], "little", signed=True))
            self.tpdo1_frames += 1

    def latest_counts(self, n: int) -> tuple[int, int] | None:
        with self._lock:
            return self.counts.get(n)

    def rpdo1(self, n: int, traction_permille: int, steer_counts: int) -> None:
        self.net.send_message(0x200 + n, traction_permille.to_bytes(4, "little", signed=True)
                              + steer_counts.to_bytes(4, "little", signed=True))

    def close(self) -> None:
        self.net.disconnect()


def test_master_drives_both_modules_and_the_watchdog_stops_them(stack_factory) -> None:
    stack = stack_factory(services=["sim"]).start()
    truth: list[GroundTruth] = []
    lock = threading.Lock()

    def on_truth(sample) -> None:
        msg = codec.decode_as(GroundTruth, sample.payload.to_bytes())
        with lock:
            truth.append(msg)

    session = stack.session()
    sub = session.declare_subscriber(stack.keys("sim/ground_truth"), on_truth)
    master = Master(f"ws://127.0.0.1:{stack.can_port}/")
    try:
        # boot: both nodes answer in PRE-OPERATIONAL; NMT start puts them in OPERATIONAL
        for node in master.nodes.values():
            assert node.nmt.wait_for_heartbeat(timeout=5) == "PRE-OPERATIONAL"
            assert int.from_bytes(node.sdo.upload(0x1018, 1), "little") == 0x469
        master.net.nmt.send_command(0x01)
        for node in master.nodes.values():
            wait_for_sync(lambda node=node: node.nmt.wait_for_heartbeat(timeout=2) == "OPERATIONAL", timeout_s=5)
        wait_for_sync(lambda: master.latest_counts(1) and master.latest_counts(2), timeout_s=5)
        start_counts = {n: master.latest_counts(n) for n in (1, 2)}
        with lock:
            start_pose = truth[-1].pose

        # steer both wheels to +90 degrees (SDO write of !P), traction still
        quarter = round(UNITS.rad_to_counts(math.pi / 2))
        for n, node in master.nodes.items():
            node.sdo.download(0x2001, 2, (start_counts[n][1] + quarter).to_bytes(4, "little", signed=True))
        wait_for_sync(lambda: all(abs(master.latest_counts(n)[1] - start_counts[n][1] - quarter) <= 1
                                  for n in (1, 2)), timeout_s=10, message="steering did not reach +90 deg")

        # drive sideways with RPDO1 (traction 200 per mille of MXRPM) for a while, refreshing the watchdog
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            for n in (1, 2):
                master.rpdo1(n, 200, start_counts[n][1] + quarter)
            time.sleep(0.05)
        speed_rpm = int.from_bytes(master.nodes[1].sdo.upload(0x2103, 1), "little", signed=True)
        assert speed_rpm == pytest.approx(0.2 * CFG.traction_max_rpm, abs=5)
        for n in (1, 2):
            master.rpdo1(n, 0, start_counts[n][1] + quarter)

        def still() -> bool:
            with lock:
                return len(truth) > 5 and all(abs(t.twist.vy) < 1e-4 for t in truth[-5:])

        wait_for_sync(still, timeout_s=10, message="robot did not stop after a zero command")
        time.sleep(0.1)
        with lock:
            pose = truth[-1].pose
        travelled = {n: UNITS.counts_to_m(master.latest_counts(n)[0] - start_counts[n][0]) for n in (1, 2)}
        dx, dy = pose.x - start_pose.x, pose.y - start_pose.y
        assert travelled[1] > 0.2
        assert math.hypot(dx, dy) == pytest.approx(travelled[1], abs=0.005)
        assert travelled[2] == pytest.approx(travelled[1], abs=0.005)
        assert math.atan2(dy, dx) == pytest.approx(math.pi / 2, abs=0.01)
        assert pose.theta == pytest.approx(start_pose.theta, abs=0.01)

        # watchdog: drive again, then stop sending; the wheels stop one RWD period (1 s) after the last command
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            for n in (1, 2):
                master.rpdo1(n, 200, start_counts[n][1] + quarter)
            time.sleep(0.05)
        with lock:
            n_before = len(truth)
            last_command_s = truth[-1].stamp
        wait_for_sync(still, timeout_s=10, message="wheels kept turning without commands")
        with lock:
            after = truth[n_before:]
        moving = [t.stamp for t in after if abs(t.twist.vy) > 0.05]
        stopped_at = next(t.stamp for t in after if abs(t.twist.vy) < 1e-4)
        assert moving and max(moving) - last_command_s > 0.8, "stopped before the RWD period"
        assert stopped_at - last_command_s < CFG.watchdog_ms / 1000 + 0.6, "stopped too late"
        assert int.from_bytes(master.nodes[1].sdo.upload(0x2103, 1), "little", signed=True) == 0
    finally:
        master.close()
        sub.undeclare()
