"""Lidar node: LMS111 over CoLa A/TCP -> ``scan`` (LaserScan, frame ``laser``, stamped with the device clock mapped
onto the service clock, services.lidar.timesync).

Per connection: SetAccessMode -> LMPscancfg (mLMPsetscancfg when frequency/resolution differ) -> LMDscandatacfg ->
LMCstartmeas -> STlms until 7 -> Run -> ``sEN LMDscandata 1``, then every ``sSN LMDscandata`` becomes a LaserScan.
A lost connection, a refused step or a silent scanner (watchdog) closes the link; the node reconnects with
exponential backoff (wall time: it measures the link, and must work while a simulator's clock is stopped).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time

from proto.messages import LaserScan, Pose2D
from services.common.clock import Clock
from services.common.node import Node
from services.lidar.cola import (
    ColaError,
    DeviceError,
    cmd_login,
    cmd_method,
    cmd_read,
    cmd_scandata_config,
    cmd_set_scan_config,
    cmd_stream,
)
from services.lidar.config import LidarConfig
from services.lidar.convert import to_laserscan
from services.lidar.link import ColaLink, LinkLost
from services.lidar.telegrams import (
    ScanConfig,
    decode_device_state,
    decode_method_result,
    decode_scancfg,
    decode_scandata,
)
from services.lidar.timesync import DeviceClockSync
from services.lidar.watchdog import ScanWatchdog

READY_FOR_MEASUREMENT = 7


class LidarSetupError(ColaError):
    """The scanner refused a setup step (login, scan configuration, start)."""


class LidarNode:
    """Owns the scanner link and the ``scan`` publisher; ``await run(stop)`` until ``stop`` is set."""

    def __init__(self, node: Node, config: LidarConfig, mount: Pose2D) -> None:
        self.node = node
        self.config = config
        self.mount = mount
        self.clock: Clock = node.clock
        self.log = node.log
        self.pub = node.publisher("scan")
        self.scans = 0
        self.bad_scans = 0
        self.connects = 0
        self.scanner_config: ScanConfig | None = None
        self.last_error = ""
        self._bad_logged_at = -math.inf
        self._failure_logged_at = -math.inf
        self.link: ColaLink | None = None
        node.extra_stats["lidar"] = self.stats()

    def stats(self) -> dict[str, object]:
        link = self.link
        return {
            "scans": self.scans,
            "bad_scans": self.bad_scans,
            "connects": self.connects,
            "framing_errors": link.framing_errors if link else 0,
            "bad_telegrams": link.bad_telegrams if link else 0,
            "last_error": self.last_error,
            "scanner": f"{self.scanner_config.frequency_hz:g} Hz, {self.scanner_config.resolution_deg:g} deg"
            if self.scanner_config else "",
        }

    def _update_stats(self) -> None:
        self.node.extra_stats["lidar"] = self.stats()

    async def run(self, stop: asyncio.Event) -> None:
        cfg = self.config
        backoff = cfg.reconnect_min_s
        while not stop.is_set():
            started_scans = self.scans
            try:
                await self._session(stop)
            except (LinkLost, ColaError, OSError) as exc:
                # the same failure again (a scanner still booting) is logged at most every 30 s
                now = time.monotonic()
                if str(exc) != self.last_error or now - self._failure_logged_at > 30.0:
                    self._failure_logged_at = now
                    self.log.warning("LMS111 at %s:%d: %s; reconnecting in %.1f s", cfg.host, cfg.port, exc,
                                     backoff)
                self.last_error = str(exc)
            except Exception as exc:  # a bug must not end the service: report it and start a new session
                self.last_error = f"{type(exc).__name__}: {exc}"
                self.log.exception("LMS111 session failed; reconnecting in %.1f s", backoff)
            finally:
                self._close_link()
                self._update_stats()
                self.node.ready(f"LMS111 link down: {self.last_error}")  # the first attempt's outcome is known
            if stop.is_set():
                break
            if self.scans > started_scans:
                backoff = cfg.reconnect_min_s  # the link worked: start again from the shortest delay
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), backoff)  # wall time: link retry, not robot timing
            backoff = min(backoff * 2.0, cfg.reconnect_max_s)

    def _close_link(self) -> None:
        link = self.link
        if link is not None:
            with contextlib.suppress(Exception):
                link.writer.write(cmd_stream(False))  # best effort: stop streaming before closing
            link.close()

    async def _session(self, stop: asyncio.Event) -> None:
        cfg = self.config
        self.link = link = await ColaLink.connect(cfg.host, cfg.port, connect_timeout_s=cfg.connect_timeout_s,
                                                  reply_timeout_s=cfg.reply_timeout_s,
                                                  max_telegram_bytes=cfg.max_telegram_bytes)
        self.connects += 1
        self.log.info("connected to LMS111 at %s:%d", cfg.host, cfg.port)
        await self._setup(link)
        assert self.scanner_config is not None  # _setup read it from the device
        self.log.info("LMS111 streaming %g Hz at %g deg", self.scanner_config.frequency_hz,
                      self.scanner_config.resolution_deg)
        await self._stream(link, stop)

    async def _setup(self, link: ColaLink) -> None:
        cfg = self.config
        if decode_method_result(await link.request(cmd_login(cfg.login_level, cfg.login_password_hash)),
                                "SetAccessMode") != 1:
            raise LidarSetupError(f"login refused (level {cfg.login_level}, check lidar.login_password_hash)")
        current = decode_scancfg(await link.request(cmd_read("LMPscancfg")))
        if cfg.apply_scan_config and not self._matches(current):
            self.log.info("LMS111 runs %g Hz at %g deg; setting %g Hz at %g deg", current.frequency_hz,
                          current.resolution_deg, cfg.frequency_hz, cfg.resolution_deg)
            result = decode_scancfg(await link.request(cmd_set_scan_config(cfg.frequency_hz, cfg.resolution_deg)))
            if result.status != 0:
                raise LidarSetupError(f"mLMPsetscancfg {cfg.frequency_hz:g} Hz {cfg.resolution_deg:g} deg refused "
                                      f"with status {result.status}")
            current = decode_scancfg(await link.request(cmd_read("LMPscancfg")))
        if not self._matches(current):
            self.log.warning("LMS111 runs %g Hz at %g deg, not the configured %g Hz at %g deg",
                             current.frequency_hz, current.resolution_deg, cfg.frequency_hz, cfg.resolution_deg)
        self.scanner_config = current
        await link.request(cmd_scandata_config(intensities=cfg.intensities))
        status = decode_method_result(await link.request(cmd_method("LMCstartmeas")), "LMCstartmeas")
        if status != 0:
            raise LidarSetupError(f"LMCstartmeas failed with status {status}")
        await self._wait_ready(link)
        if decode_method_result(await link.request(cmd_method("Run")), "Run") != 1:
            raise LidarSetupError("Run refused")
        await link.request(cmd_stream(True))

    def _matches(self, current: ScanConfig) -> bool:
        return (abs(current.frequency_hz - self.config.frequency_hz) < 1e-6
                and abs(current.resolution_deg - self.config.resolution_deg) < 1e-6)

    async def _wait_ready(self, link: ColaLink) -> None:
        """Poll STlms until the device is ready for measurement (7); wall time (the device's own start-up)."""
        deadline = time.monotonic() + self.config.ready_timeout_s
        while True:
            try:
                state = decode_device_state(await link.request(cmd_read("STlms")))
            except DeviceError:
                return  # a device without STlms: go on, the watchdog judges the stream
            if state == READY_FOR_MEASUREMENT:
                return
            if time.monotonic() > deadline:
                raise LidarSetupError(f"device state {state}, not ready for measurement (7) after "
                                      f"{self.config.ready_timeout_s} s")
            await asyncio.sleep(0.2)

    async def _stream(self, link: ColaLink, stop: asyncio.Event) -> None:
        cfg = self.config
        watchdog = ScanWatchdog(cfg.watchdog_timeout_s)
        device_clock = DeviceClockSync()  # per connection: a reconnect may follow a device reboot
        watchdog.feed(self.clock.now(), time.monotonic())
        poll_s = min(cfg.watchdog_timeout_s / 4.0, 0.25)
        while not stop.is_set():
            reply = await link.next_reply(poll_s)
            if reply is not None and reply.name == "LMDscandata" and reply.kind in ("sSN", "sRA"):
                receive = self.clock.now()
                try:
                    scan = decode_scandata(reply)
                    stamp = device_clock.stamp(receive, scan.time_since_startup_us, scan.time_of_transmission_us)
                    msg = to_laserscan(scan, stamp=stamp, range_min_m=cfg.range_min_m, range_max_m=cfg.range_max_m,
                                       mount=self.mount, intensities=cfg.intensities)
                except ColaError as exc:
                    self._bad_scan(exc)
                else:
                    self._publish(msg)
                    watchdog.feed(receive, time.monotonic())
            if watchdog.expired(self.clock.now(), time.monotonic()):
                raise LinkLost(f"no scan for {watchdog.silence_s(time.monotonic()):.1f} s (watchdog "
                               f"{cfg.watchdog_timeout_s} s)")

    def _publish(self, msg: LaserScan) -> None:
        self.pub.put(msg)
        self.scans += 1
        if self.scans == 1:
            self.node.ready("LMS111 streaming")
        if self.scans % 25 == 1:
            self._update_stats()

    def _bad_scan(self, exc: Exception) -> None:
        self.bad_scans += 1
        self.last_error = str(exc)
        now = time.monotonic()
        if now - self._bad_logged_at >= 1.0:  # rate-limited: a garbled stream must not flood the log
            self._bad_logged_at = now
            self.log.warning("dropped bad LMDscandata #%d: %s", self.bad_scans, exc)


async def run(ctx) -> None:  # services.common.service.ServiceContext
    config: LidarConfig = ctx.config["lidar"]
    lidar = LidarNode(ctx.node, config, config.mount(ctx.robot))
    logging.getLogger("zagv.lidar").info("LMS111 at %s:%d, %g Hz, %g deg", config.host, config.port,
                                         config.frequency_hz, config.resolution_deg)
    await lidar.run(ctx.stop)
