"""Razor 9DOF IMU with the Razor AHRS firmware over serial (protocols.md §4).

Start-up as the ROS ``razor_imu_9dof`` node does: ``#o0`` (stop streaming), ``#ox`` (angles + accel + gyro, text),
``#o1`` (stream). Each line ``#YPRAG=yaw,pitch,roll,ax,ay,az,gx,gy,gz`` carries angles in degrees (firmware axes:
X forward, Y right, Z down; yaw clockwise positive), acceleration in 1/256 g and angular rates in rad/s. Converted
to REP-103 (X forward, Y left, Z up): yaw = -yaw, pitch = -pitch, roll = roll (rad); a = (-ax, ay, az) * 9.806/256;
w = (gx, -gy, -gz).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from services.common.se2 import wrap_angle

log = logging.getLogger("zagv.drive.imu")

PREFIX = "#YPRAG="
G_PER_LSB = 9.806 / 256.0


@dataclass(frozen=True, slots=True)
class ImuSample:
    """REP-103 orientation (rad), angular velocity (rad/s) and linear acceleration (m/s^2)."""

    yaw: float
    pitch: float
    roll: float
    angular_velocity: tuple[float, float, float]
    linear_acceleration: tuple[float, float, float]


class ImuParseError(ValueError):
    """A line that is not a well-formed ``#YPRAG=`` record (the reason says why)."""


def parse_line(line: str) -> ImuSample:
    """Parse one ``#YPRAG=`` line (with or without its CR LF) into REP-103 units."""
    text = line.strip()
    if not text.startswith(PREFIX):
        raise ImuParseError(f"not a {PREFIX} line: {text[:40]!r}")
    parts = text[len(PREFIX):].split(",")
    if len(parts) != 9:
        raise ImuParseError(f"{PREFIX} needs 9 values, got {len(parts)}")
    try:
        v = [float(p) for p in parts]
    except ValueError:
        raise ImuParseError(f"{PREFIX} has a non-numeric value: {text[:80]!r}") from None
    if not all(math.isfinite(x) for x in v):
        raise ImuParseError(f"{PREFIX} has a non-finite value: {text[:80]!r}")
    yaw, pitch, roll, ax, ay, az, gx, gy, gz = v
    return ImuSample(wrap_angle(math.radians(-yaw)), math.radians(-pitch), math.radians(roll), (gx, -gy, -gz),
                     (-ax * G_PER_LSB, ay * G_PER_LSB, az * G_PER_LSB))


class RazorReader:
    """Reads the IMU on its own thread and calls ``on_sample`` for each good line; reopens the port on errors."""

    def __init__(self, port: str, baud: int, on_sample: Callable[[ImuSample], None],
                 reopen_s: float = 1.0) -> None:
        self.port = port
        self.baud = baud
        self.on_sample = on_sample
        self.reopen_s = reopen_s
        self.samples = 0
        self.bad_lines = 0
        self.error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="drive-imu", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def _run(self) -> None:
        import serial  # pyserial

        while not self._stop.is_set():
            try:
                with serial.Serial(self.port, self.baud, timeout=0.2) as ser:
                    # stale input goes before the commands, not after: a flush after them could drop the first
                    # lines the firmware sends in answer
                    ser.reset_input_buffer()
                    ser.write(b"#o0#ox#o1")
                    self.error = ""
                    self._read_lines(ser)
            except (OSError, serial.SerialException) as exc:
                if self.error != str(exc):
                    log.warning("IMU %s: %s; retrying every %.1f s", self.port, exc, self.reopen_s)
                self.error = str(exc)
                self._stop.wait(self.reopen_s)

    def _read_lines(self, ser: Any) -> None:
        """Read ``#YPRAG=`` lines from ``ser`` (a serial.Serial) until stopped."""
        buf = b""
        while not self._stop.is_set():
            chunk = ser.read(ser.in_waiting or 1)
            if not chunk:
                continue
            buf += chunk
            *lines, buf = buf.split(b"\n")
            if len(buf) > 4096:  # garbage without line ends
                buf = b""
            for raw in lines:
                text = raw.decode("ascii", errors="replace")
                if not text.startswith(PREFIX):
                    continue  # echoes, #SYNCH, calibration prints
                try:
                    sample = parse_line(text)
                except ImuParseError as exc:
                    self.bad_lines += 1
                    if self.bad_lines % 100 == 1:
                        log.warning("IMU: %s (%d bad lines)", exc, self.bad_lines)
                    continue
                self.samples += 1
                self.on_sample(sample)
