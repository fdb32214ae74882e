"""Emulated SparkFun 9DOF Razor IMU running the Razor AHRS firmware (protocols.md §4).

Pure core: ``RazorImu.feed(data)`` parses host commands and returns the bytes to answer; ``frame(...)`` returns
the output line for the current truth when streaming. Firmware conventions: text output
``#YPR=<yaw>,<pitch>,<roll>\\r\\n`` in degrees with yaw positive **clockwise** (X forward, Y right, Z down), so the
emitted yaw is minus the REP-103 heading. ``#ox`` selects ``#YPRAG=yaw,pitch,roll,ax,ay,az,gx,gy,gz`` (accel in
1/256 g, gyro rad/s, firmware axes). The yaw integrates the true turn rate plus a constant gyro bias and white
noise (seeded), so it drifts as a real gyro-integrated yaw does. Commands: ``#o0``/``#o1`` stop/start streaming,
``#ot`` text angles, ``#ox`` angles+accel+gyro, ``#f`` one frame, ``#s<xy>`` -> ``#SYNCH<xy>\\r\\n``; others
are ignored.
"""

from __future__ import annotations

import math

import numpy as np

from services.common.se2 import wrap_angle

G = 9.806


class RazorImu:
    """Yaw from integrated gyro (true rate + bias + noise); pitch and roll 0 (a planar robot)."""

    def __init__(self, gyro_bias_radps: float = 0.0, gyro_noise_radps: float = 0.0, seed: int = 0,
                 initial_yaw_rad: float = 0.0) -> None:
        self.bias = gyro_bias_radps
        self.noise = gyro_noise_radps
        self._rng = np.random.default_rng(seed)
        self.yaw_rad = initial_yaw_rad  # REP-103 (counter-clockwise positive), as integrated by the IMU
        self.rate_radps = 0.0
        self.streaming = True
        self.mode = "ot"
        self._pending_frame = False
        self._buf = b""

    def integrate(self, true_wz_radps: float, dt_s: float) -> None:
        """Advance the yaw by the measured rate over ``dt_s``."""
        self.rate_radps = true_wz_radps + self.bias + (self.noise * float(self._rng.standard_normal())
                                                       if self.noise else 0.0)
        self.yaw_rad = wrap_angle(self.yaw_rad + self.rate_radps * dt_s)

    def feed(self, data: bytes) -> bytes:
        """Parse command bytes from the host; returns immediate replies (``#s`` sync answers)."""
        self._buf = (self._buf + data)[-256:]
        out = b""
        while True:
            start = self._buf.find(b"#")
            if start < 0:
                self._buf = b""
                return out
            buf = self._buf[start:]
            if len(buf) < 2:
                self._buf = buf
                return out
            c = buf[1:2]
            if c == b"o":
                if len(buf) < 3:
                    self._buf = buf
                    return out
                sub = buf[2:3]
                consumed = 3
                if sub == b"0":
                    self.streaming = False
                elif sub == b"1":
                    self.streaming = True
                elif sub in (b"t", b"x"):
                    self.mode = "o" + sub.decode()
                elif sub == b"s" or sub == b"e":  # #osct.. / #oe0: sensor modes and error output, 4 chars
                    consumed = 4 if len(buf) >= 4 else len(buf)
                self._buf = buf[consumed:]
            elif c == b"f":
                self._pending_frame = True
                self._buf = buf[2:]
            elif c == b"s":
                if len(buf) < 4:
                    self._buf = buf
                    return out
                out += b"#SYNCH" + buf[2:4] + b"\r\n"
                self._buf = buf[4:]
            else:
                self._buf = buf[2:]

    def due_frame(self) -> bytes | None:
        """The line to send at this 20 ms tick, or None (streaming off and no ``#f`` pending)."""
        if not (self.streaming or self._pending_frame):
            return None
        self._pending_frame = False
        return self.line()

    def line(self) -> bytes:
        yaw_deg = -math.degrees(self.yaw_rad)  # firmware: clockwise positive
        if self.mode == "ox":
            gz = -self.rate_radps  # firmware Z axis points down
            return (f"#YPRAG={yaw_deg:.2f},0.00,0.00,0.00,0.00,256.00,0.0000,0.0000,{gz:.4f}\r\n").encode()
        return f"#YPR={yaw_deg:.2f},0.00,0.00\r\n".encode()
