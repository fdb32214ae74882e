"""Decoders of the LMS1xx replies the client uses: ``LMDscandata`` (protocols.md §3.3), ``LMPscancfg``, ``STlms``.

Every decoder takes a ``Reply`` (see ``cola.parse_reply``) and raises ``ColaError`` naming the field and token when
the telegram does not follow the layout; it never raises anything else, whatever the bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.lidar.cola import ColaError, Reply, Tokens, check_not_error, parse_int32, parse_real32, parse_uint


@dataclass(frozen=True)
class ScanConfig:
    """``LMPscancfg``: scan frequency (Hz), sectors, angular resolution and start/stop angle (SICK degrees)."""

    frequency_hz: float
    sectors: int
    resolution_deg: float
    start_deg: float
    stop_deg: float
    status: int = 0  # mLMPsetscancfg status (0 = OK); 0 for a plain read

    @property
    def points(self) -> int:
        """Beams in the full sector: (stop - start) / resolution + 1 (541 for 270 deg at 0.5 deg)."""
        return round((self.stop_deg - self.start_deg) / self.resolution_deg) + 1


@dataclass(frozen=True)
class Channel:
    """One output channel (``DIST1``, ``RSSI1`` ...): raw values, scale/offset, start angle and step (SICK deg)."""

    content: str
    scale: float
    offset: float
    start_angle_raw: int  # 1/10000 deg, S32
    step_raw: int  # 1/10000 deg
    values: np.ndarray  # raw U16/U8 values as int64
    bits: int  # 16 or 8

    @property
    def scaled(self) -> np.ndarray:
        """value * scale + offset (mm for DIST channels on an LMS1xx) as float64."""
        return self.values * self.scale + self.offset


@dataclass(frozen=True)
class ScanData:
    """Every field of an ``LMDscandata`` telegram (protocols.md §3.3); optional blocks are None when absent."""

    streamed: bool  # sSN (event) rather than sRA (polled)
    version: int
    device_number: int
    serial_number: int
    device_status: tuple[int, int]
    telegram_counter: int
    scan_counter: int
    time_since_startup_us: int  # device clock at the first beam
    time_of_transmission_us: int
    digital_inputs: tuple[int, int]
    digital_outputs: tuple[int, int]
    layer_angle: int
    scan_frequency_raw: int  # 1/100 Hz
    measurement_frequency_raw: int  # 100 Hz units
    encoders: list[tuple[int, int]] = field(default_factory=list)  # (position, speed)
    channels16: list[Channel] = field(default_factory=list)
    channels8: list[Channel] = field(default_factory=list)
    position: tuple[float, ...] | None = None  # x, y, z, rot x, rot y, rot z, rotation type
    device_name: str | None = None
    comment: str | None = None
    timestamp: tuple[int, int, int, int, int, int, int] | None = None  # year, month, day, h, min, s, us
    event: tuple[str, int, int, int] | None = None  # type, encoder position, time, angle

    @property
    def scan_frequency_hz(self) -> float:
        return self.scan_frequency_raw / 100.0

    @property
    def measurement_frequency_hz(self) -> float:
        return self.measurement_frequency_raw * 100.0

    def channel(self, content: str) -> Channel | None:
        """The first channel with this content (16-bit section first), or None."""
        for ch in (*self.channels16, *self.channels8):
            if ch.content == content:
                return ch
        return None

    @property
    def transmission_delay_s(self) -> float:
        """Device time from the first beam to transmission (U32 µs counters, modulo wrap-around)."""
        return ((self.time_of_transmission_us - self.time_since_startup_us) % 2**32) * 1e-6


class _Cursor:
    """Sequential reader over a telegram's tokens, naming each field in its errors."""

    __slots__ = ("t", "i")

    def __init__(self, tokens: Tokens, start: int) -> None:
        self.t = tokens
        self.i = start

    def at_end(self) -> bool:
        return self.i >= self.t.count

    def raw(self, what: str) -> bytes:
        if self.i >= self.t.count:
            raise ColaError(f"LMDscandata ends before {what} (token {self.i})")
        tok = self.t[self.i]
        self.i += 1
        return tok

    def uint(self, what: str, digits: int = 8) -> int:
        return parse_uint(self.raw(what), f"LMDscandata {what} (token {self.i - 1})", digits)

    def int32(self, what: str) -> int:
        return parse_int32(self.raw(what), f"LMDscandata {what} (token {self.i - 1})")

    def real32(self, what: str) -> float:
        return parse_real32(self.raw(what), f"LMDscandata {what} (token {self.i - 1})")

    def string(self, what: str) -> str:
        """``<len> <chars>``; the text may itself contain spaces, so tokens are joined until the length fits."""
        length = self.uint(f"{what} length", 4)
        if length == 0:
            return ""
        text = self.raw(what)
        while len(text) < length and not self.at_end():
            text += b" " + self.raw(what)
        if len(text) != length:
            raise ColaError(f"LMDscandata {what}: length {length} does not match {text[:40]!r}")
        return text.decode("latin-1")

    def values(self, count: int, what: str, digits: int) -> np.ndarray:
        out = self.t.hex_array(self.i, count, f"LMDscandata {what}", digits)
        self.i += count
        return out


def _channel(cur: _Cursor, bits: int) -> Channel:
    content = cur.raw("channel content")
    if len(content) != 5 or not content.isalnum() or not content.isascii():
        raise ColaError(f"LMDscandata channel content {content[:24]!r} is not a 5-character name such as DIST1")
    name = content.decode("ascii")
    scale = cur.real32(f"{name} scale factor")
    offset = cur.real32(f"{name} scale offset")
    if not (np.isfinite(scale) and np.isfinite(offset)):
        raise ColaError(f"LMDscandata {name}: scale {scale} / offset {offset} is not finite")
    start = cur.int32(f"{name} start angle")
    step = cur.uint(f"{name} angular step", 4)
    count = cur.uint(f"{name} number of data", 4)
    values = cur.values(count, f"{name} data", 4 if bits == 16 else 2)
    return Channel(name, scale, offset, start, step, values, bits)


def decode_scandata(reply: Reply) -> ScanData:
    """Decode an ``sRA``/``sSN LMDscandata`` reply (field numbers as in protocols.md §3.3)."""
    check_not_error(reply, "LMDscandata")
    if reply.name != "LMDscandata" or reply.kind not in ("sRA", "sSN"):
        raise ColaError(f"expected sRA/sSN LMDscandata, got {reply.kind} {reply.name}")
    c = _Cursor(reply.tokens, 2)
    version = c.uint("version number", 4)
    device_number = c.uint("device number", 4)
    serial = c.uint("serial number")
    status = (c.uint("device status", 2), c.uint("device status", 2))
    telegram_counter = c.uint("telegram counter", 4)
    scan_counter = c.uint("scan counter", 4)
    t_first = c.uint("time since start-up")
    t_tx = c.uint("time of transmission")
    inputs = (c.uint("digital inputs", 2), c.uint("digital inputs", 2))
    outputs = (c.uint("digital outputs", 2), c.uint("digital outputs", 2))
    layer = c.uint("reserved/layer angle", 4)
    freq = c.uint("scan frequency")
    meas = c.uint("measurement frequency")
    n_enc = c.uint("number of encoders", 4)
    if n_enc > 8:
        raise ColaError(f"LMDscandata number of encoders {n_enc} is implausible (> 8)")
    encoders = [(c.uint("encoder position"), c.uint("encoder speed", 4)) for _ in range(n_enc)]
    n16 = c.uint("number of 16-bit channels", 4)
    if n16 > 8:
        raise ColaError(f"LMDscandata number of 16-bit channels {n16} is implausible (> 8)")
    ch16 = [_channel(c, 16) for _ in range(n16)]
    ch8: list[Channel] = []
    position = name = comment = timestamp = event = None
    # the trailing blocks are optional: a telegram may end after any of them
    if not c.at_end():
        n8 = c.uint("number of 8-bit channels", 4)
        if n8 > 8:
            raise ColaError(f"LMDscandata number of 8-bit channels {n8} is implausible (> 8)")
        ch8 = [_channel(c, 8) for _ in range(n8)]
    if not c.at_end() and c.uint("position flag", 4):
        position = (*(c.real32("position") for _ in range(6)), float(c.uint("rotation type", 2)))
    if not c.at_end() and c.uint("device-name flag", 4):
        name = c.string("device name")
    if not c.at_end() and c.uint("comment flag", 4):
        comment = c.string("comment")
    if not c.at_end() and c.uint("time flag", 4):
        timestamp = (c.uint("year", 4), c.uint("month", 2), c.uint("day", 2), c.uint("hour", 2),
                     c.uint("minute", 2), c.uint("second", 2), c.uint("microseconds"))
    if not c.at_end() and c.uint("event flag", 4):
        event = (c.raw("event type").decode("latin-1"), c.uint("event encoder position"), c.uint("event time"),
                 c.int32("event angle"))
    return ScanData(
        streamed=reply.kind == "sSN", version=version, device_number=device_number, serial_number=serial,
        device_status=status, telegram_counter=telegram_counter, scan_counter=scan_counter,
        time_since_startup_us=t_first, time_of_transmission_us=t_tx, digital_inputs=inputs,
        digital_outputs=outputs, layer_angle=layer, scan_frequency_raw=freq, measurement_frequency_raw=meas,
        encoders=encoders, channels16=ch16, channels8=ch8, position=position, device_name=name, comment=comment,
        timestamp=timestamp, event=event,
    )


def decode_scancfg(reply: Reply) -> ScanConfig:
    """``sRA LMPscancfg <freq> <sectors> <res> <start> <stop>`` or ``sAN mLMPsetscancfg <status> <same...>``."""
    check_not_error(reply, reply.name or "LMPscancfg")
    t = reply.tokens
    if reply.kind == "sRA" and reply.name == "LMPscancfg":
        first, status = 2, 0
    elif reply.kind == "sAN" and reply.name == "mLMPsetscancfg":
        first = 3
        status = parse_uint(t[2], "mLMPsetscancfg status")
        if t.count <= 3:  # some firmware answers only the status
            return ScanConfig(0.0, 0, 0.0, 0.0, 0.0, status)
    else:
        raise ColaError(f"expected sRA LMPscancfg or sAN mLMPsetscancfg, got {reply.kind} {reply.name}")
    freq = parse_uint(t[first], "LMPscancfg scan frequency")
    sectors = parse_uint(t[first + 1], "LMPscancfg number of sectors", 4)
    res = parse_uint(t[first + 2], "LMPscancfg angular resolution")
    start = parse_int32(t[first + 3], "LMPscancfg start angle")
    stop = parse_int32(t[first + 4], "LMPscancfg stop angle")
    if res == 0:
        raise ColaError("LMPscancfg angular resolution is 0")
    return ScanConfig(freq / 100.0, sectors, res / 10000.0, start / 10000.0, stop / 10000.0, status)


def decode_device_state(reply: Reply) -> int:
    """``sRA STlms <state> ...``: the device state (7 = ready for measurement)."""
    check_not_error(reply, "STlms")
    if reply.kind != "sRA" or reply.name != "STlms":
        raise ColaError(f"expected sRA STlms, got {reply.kind} {reply.name}")
    return parse_uint(reply.tokens[2], "STlms device state", 2)


def decode_method_result(reply: Reply, method: str) -> int:
    """``sAN <method> <result>``: the method's numeric result (its meaning depends on the method)."""
    check_not_error(reply, method)
    if reply.kind not in ("sAN", "sMA") or reply.name != method:
        raise ColaError(f"expected sAN {method}, got {reply.kind} {reply.name}")
    return parse_uint(reply.tokens[2], f"{method} result") if reply.tokens.count > 2 else 0
