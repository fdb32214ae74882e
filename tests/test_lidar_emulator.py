"""The emulated LMS111 against the lidar service's CoLa A client code, with an analytic scan source."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from proto.messages import Pose2D
from services.common.clock import SimClock, WallClock
from services.lidar.cola import (
    DeviceError,
    cmd_login,
    cmd_method,
    cmd_read,
    cmd_scandata_config,
    cmd_set_scan_config,
    cmd_stream,
    frame,
)
from services.lidar.convert import to_laserscan
from services.lidar.link import ColaLink
from services.lidar.telegrams import decode_device_state, decode_method_result, decode_scancfg, decode_scandata
from services.sim.lms111 import Lms111Emulator
from tests.support.waiting import wait_for


class CircleRoom:
    """A round room of ``radius_m`` whose centre is at (cx, cy) in the laser frame, with a doorway (no return)
    between ``door_rad`` angles. ``laser_ranges`` solves |p + t d| = R for the beam direction d."""

    def __init__(self, clock, radius_m: float = 6.0, centre=(-0.8, 1.5), door_rad=(-0.5, -0.3)) -> None:
        self.clock = clock
        self.radius_m = radius_m
        self.centre = np.asarray(centre, dtype=float)
        self.door_rad = door_rad
        self.calls = 0

    def expected(self, angles_rad: np.ndarray) -> np.ndarray:
        p = -self.centre  # the laser relative to the room centre
        d = np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=1)
        pd = d @ p
        t = -pd + np.sqrt(pd**2 - p @ p + self.radius_m**2)
        return np.where((angles_rad > self.door_rad[0]) & (angles_rad < self.door_rad[1]), np.inf, t)

    def laser_ranges(self, angles_rad: np.ndarray) -> tuple[float, np.ndarray]:
        self.calls += 1
        return self.clock.now(), self.expected(angles_rad)


def check_ranges(ls, room: CircleRoom, noise_m: float) -> None:
    """The decoded LaserScan agrees with the room: every finite beam within 5 sigma + 1 mm, the doorway is +inf."""
    ranges = np.frombuffer(ls.ranges, "<f4").astype(float)
    angles = ls.angle_min + ls.angle_increment * np.arange(ranges.size)
    truth = room.expected(angles)
    door = ~np.isfinite(truth)
    assert door.any() and np.all(ranges[door] == np.inf)
    assert np.max(np.abs(ranges[~door] - truth[~door])) < 5 * noise_m + 0.0011


@pytest.fixture
async def lms():
    emulators: list[Lms111Emulator] = []

    async def make(clock=None, **kwargs) -> tuple[Lms111Emulator, CircleRoom]:
        clock = clock or WallClock()
        room = CircleRoom(clock)
        emu = Lms111Emulator("127.0.0.1", 0, room, clock, **kwargs)
        await emu.start()
        emulators.append(emu)
        return emu, room

    yield make
    for emu in emulators:
        await emu.stop()


@pytest.fixture
async def links():
    opened: list[ColaLink] = []

    async def connect(emu: Lms111Emulator) -> ColaLink:
        link = await ColaLink.connect("127.0.0.1", emu.port, connect_timeout_s=3, reply_timeout_s=3,
                                      max_telegram_bytes=65536)
        opened.append(link)
        return link

    yield connect
    for link in opened:
        link.close()


async def test_login_and_access_rules(lms, links):
    emu, _ = await lms()
    link = await links(emu)
    with pytest.raises(DeviceError) as exc:
        await link.request(cmd_set_scan_config(50, 0.5))
    assert exc.value.code == 1  # method access denied before login
    with pytest.raises(DeviceError) as exc:
        await link.request(cmd_scandata_config(intensities=True))
    assert exc.value.code == 10  # variable write access denied
    assert decode_method_result(await link.request(cmd_login(3, "DEADBEEF")), "SetAccessMode") == 0
    assert decode_method_result(await link.request(cmd_login(3, "f4724744")), "SetAccessMode") == 1
    assert decode_method_result(await link.request(cmd_method("LMCstartmeas")), "LMCstartmeas") == 0
    assert decode_method_result(await link.request(cmd_method("Run")), "Run") == 1
    with pytest.raises(DeviceError):  # Run logged us out
        await link.request(cmd_method("LMCstopmeas"))


async def test_scan_config_read_set_and_refusals(lms, links):
    emu, _ = await lms()
    link = await links(emu)
    cfg = decode_scancfg(await link.request(cmd_read("LMPscancfg")))
    assert (cfg.frequency_hz, cfg.resolution_deg, cfg.start_deg, cfg.stop_deg, cfg.points) == (25, 0.5, -45, 225, 541)
    await link.request(cmd_login())
    set_reply = decode_scancfg(await link.request(cmd_set_scan_config(50, 0.5)))
    assert set_reply.status == 0 and set_reply.frequency_hz == 50
    assert decode_scancfg(await link.request(cmd_read("LMPscancfg"))).frequency_hz == 50
    assert decode_scancfg(await link.request(cmd_set_scan_config(50, 0.25))).status == 2  # 0.25 deg needs 25 Hz
    assert decode_scancfg(await link.request(cmd_set_scan_config(35, 0.5))).status == 1
    hexform = frame("sMN mLMPsetscancfg 9C4 1 9C4 FFF92230 225510")
    cfg = decode_scancfg(await link.request(hexform))
    assert cfg.status == 0 and cfg.resolution_deg == 0.25 and cfg.points == 1081
    assert emu.frequency_raw == 2500 and emu.resolution_raw == 2500


@pytest.mark.parametrize(("telegram", "code"), [
    (b"\x02sRN NoSuchVariable\x03", 3),
    (b"\x02sMN NoSuchMethod\x03", 2),
    (b"\x02sXX LMPscancfg\x03", 12),
    (b"\x02sEN NoSuchEvent 1\x03", 15),
    (b"\x02sMN SetAccessMode 03\x03", 5),
])
async def test_unknown_or_bad_requests_get_sfa(lms, links, telegram, code):
    emu, _ = await lms()
    link = await links(emu)
    with pytest.raises(DeviceError) as exc:
        await link.request(telegram)
    assert exc.value.code == code
    assert decode_device_state(await link.request(cmd_read("STlms"))) == 7  # the connection goes on


async def test_single_scan_is_the_room_in_sick_angles(lms, links):
    emu, room = await lms(range_noise_m=0.01, seed=3)
    link = await links(emu)
    reply = await link.request(cmd_read("LMDscandata"))
    scan = decode_scandata(reply)
    assert reply.kind == "sRA" and not scan.streamed
    dist = scan.channel("DIST1")
    assert dist.start_angle_raw == -450000 and dist.step_raw == 5000 and dist.values.size == 541
    assert scan.scan_frequency_hz == 25 and scan.measurement_frequency_hz == 18000
    ls = to_laserscan(scan, stamp=0, range_min_m=0.05, range_max_m=20, mount=Pose2D(), intensities=False)
    assert ls.angle_min == pytest.approx(-math.radians(135))
    check_ranges(ls, room, 0.01)
    # counter-clockwise: the room's centre lies to the left (+y), so the wall at +90 deg (beam 450) is farther
    ranges = np.frombuffer(ls.ranges, "<f4")
    assert ranges[450] > ranges[90] + 2.0


async def test_max_range_gives_no_echo(lms, links):
    emu, room = await lms(max_range_m=6.0, range_noise_m=0.0)
    link = await links(emu)
    scan = decode_scandata(await link.request(cmd_read("LMDscandata")))
    dist = scan.channel("DIST1")
    angles = np.radians(dist.start_angle_raw / 1e4 - 90 + dist.step_raw / 1e4 * np.arange(dist.values.size))
    truth = room.expected(angles)
    assert np.all(dist.values[truth >= 6.0] == 0)
    assert np.all(dist.values[truth < 5.9] > 0)


async def test_streaming_is_paced_on_the_given_clock(lms, links):
    clock = SimClock()
    clock.advance(0.0)
    emu, room = await lms(clock=clock)
    link = await links(emu)
    await link.request(cmd_login())
    await link.request(cmd_scandata_config(intensities=True, rssi_16bit=False, device_name=True, time_info=True))
    await link.request(cmd_method("Run"))
    assert (await link.request(cmd_stream(True))).kind == "sEA"
    await asyncio.sleep(0)
    for step in range(1, 101):  # 1.0 s of sim time in 10 ms steps (+ 5 ms: no scan due exactly at the end)
        clock.advance(step * 0.01 + 0.005)
        await asyncio.sleep(0)
    await wait_for(lambda: emu.scans_sent >= 25, timeout_s=5)
    scans = []
    while len(scans) < 25:
        reply = await link.next_reply(2.0)
        assert reply is not None
        scans.append(decode_scandata(reply))
    assert emu.scans_sent == 25  # exactly 25 Hz on the sim clock, however fast the wall clock ran
    assert all(s.streamed for s in scans)
    assert [s.scan_counter for s in scans] == list(range(scans[0].scan_counter, scans[0].scan_counter + 25))
    stamps = [s.time_since_startup_us for s in scans]
    assert np.allclose(np.diff(stamps), 40_000, atol=1)
    first = scans[0]
    assert first.channels8[0].content == "RSSI1" and first.channels8[0].values.max() <= 255
    assert first.device_name == "LMS111" and first.timestamp[:3] == (1970, 1, 1)
    ls = to_laserscan(first, stamp=0, range_min_m=0.05, range_max_m=20, mount=Pose2D(), intensities=True)
    check_ranges(ls, room, 0.01)
    assert len(ls.intensities) == len(ls.ranges)
    assert (await link.request(cmd_stream(False))).kind == "sEA"
    assert not any(c.streaming for c in emu.clients)


async def test_output_interval_and_output_range(lms, links):
    clock = SimClock()
    clock.advance(0.0)
    emu, _ = await lms(clock=clock)
    link = await links(emu)
    await link.request(cmd_login())
    await link.request(cmd_scandata_config(intensities=True, output_interval=5))
    await link.request(frame("sWN LMPoutputRange 1 1388 0 DBBA0"))  # 0 .. 90 deg SICK
    with pytest.raises(DeviceError):
        await link.request(frame("sWN LMPoutputRange 1 1388 0 DBBA1"))  # not on the 0.5 deg grid
    await link.request(cmd_stream(True))
    for step in range(1, 101):
        clock.advance(step * 0.01 + 0.005)
        await asyncio.sleep(0)
    await wait_for(lambda: emu.scans_sent >= 5, timeout_s=5)
    reply = await link.next_reply(2.0)
    scan = decode_scandata(reply)
    assert emu.scans_sent == 5  # every 5th of 25 scans
    dist, rssi = scan.channels16
    assert dist.start_angle_raw == 0 and dist.values.size == 181 and rssi.content == "RSSI1"


async def test_a_client_that_disconnects_does_not_stop_the_emulator(lms, links):
    emu, _ = await lms()
    first = await links(emu)
    await first.request(cmd_stream(True))
    first.close()
    second = await links(emu)
    await second.request(cmd_stream(True))
    reply = await second.next_reply(3.0)
    assert reply is not None and reply.kind == "sSN"
    await wait_for(lambda: len(emu.clients) == 1, timeout_s=5)


def test_invalid_construction_is_refused():
    with pytest.raises(ValueError, match="50 Hz at 0.5"):
        Lms111Emulator("127.0.0.1", 0, None, WallClock(), frequency_hz=50, resolution_deg=0.25)


class BrokenSource:
    """A scan source that fails (e.g. a world being reloaded); the emulator must stay up."""

    def laser_ranges(self, angles_rad: np.ndarray) -> tuple[float, np.ndarray]:
        raise RuntimeError("world not loaded")


async def test_a_failing_scan_source_gives_sfa_and_the_device_stays_up(links):
    clock = SimClock()
    clock.advance(0.0)
    emu = Lms111Emulator("127.0.0.1", 0, BrokenSource(), clock)
    await emu.start()
    try:
        link = await links(emu)
        with pytest.raises(DeviceError) as exc:
            await link.request(cmd_read("LMDscandata"))
        assert exc.value.code == 6
        await link.request(cmd_stream(True))
        for step in range(1, 11):
            clock.advance(step * 0.04 + 0.001)
            await asyncio.sleep(0)
        await wait_for(lambda: emu.source_failures >= 10, timeout_s=5)
        assert emu.scans_sent == 0
        assert decode_device_state(await link.request(cmd_read("STlms"))) == 7
    finally:
        await emu.stop()
