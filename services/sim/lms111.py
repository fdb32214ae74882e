"""Emulated SICK LMS111: a TCP server speaking CoLa A (protocols.md §3), scans from a ``scan_source``.

The server side of the protocol is written here on its own (the simulator imports no other service):

- framing: ``STX`` + space-separated ASCII tokens + ``ETX``; numbers in hex (negative S32 as two's complement) or
  signed decimal with an explicit sign; strings as ``<len> <chars>``;
- ``sMN SetAccessMode <level> <hash>`` -> ``sAN SetAccessMode 1|0`` (level 3 "client" F4724744, 4 "service"
  81BE23AA); configuration requests need a login, ``sMN Run`` logs out;
- ``sRN LMPscancfg`` / ``sMN mLMPsetscancfg`` (25 or 50 Hz; 0.5 deg, or 0.25 deg at 25 Hz only; 270 deg),
  ``sRN``/``sWN LMPoutputRange``, ``sWN LMDscandatacfg`` (remission 8/16 bit, device name, time info, output
  interval), ``sMN LMCstartmeas``/``LMCstopmeas``, ``sRN STlms``, ``sMN Run``, ``sMN mEEwriteall``;
- ``sRN LMDscandata`` (one scan now) and ``sEN LMDscandata 1|0`` (then ``sSN LMDscandata`` per scan);
- ``sFA <code>`` for an unknown command type (C), method (2), variable (3), event (F), a refused access (1, A),
  invalid data (5) and a failure of its own (6, e.g. the scan source raised).

Scans are paced on ``clock`` at the scan frequency. The scanner's own angles go on the wire: 90 deg is straight
ahead, counter-clockwise, -45 .. +225 deg; ``scan_source.laser_ranges(angles_rad)`` is asked in the laser frame of
REP-103 (``angle_rep103 = angle_sick - 90 deg``) and returns ``(stamp_s, ranges_m)``; a range at or beyond
``max_range_m`` (or not finite) is "no echo" and goes out as 0. Gaussian range noise (``range_noise_m``, seeded).
Distances in mm (scale factor 1.0).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import logging
from typing import Any, Protocol

import numpy as np

log = logging.getLogger("zagv.sim.lms111")

STX, ETX = b"\x02", b"\x03"
MAX_REQUEST_BYTES = 4096
MAX_CLIENT_BACKLOG_BYTES = 256 * 1024  # a client that does not read loses scans beyond this backlog

LOGIN_HASHES = {3: "F4724744", 4: "81BE23AA"}
SCAN_AREA_START = -450000  # 1/10000 deg, SICK angles
SCAN_AREA_STOP = 2250000
SICK_FORWARD_DEG = 90.0
STATE_IDLE, STATE_READY_FOR_MEASUREMENT = 3, 7

#: sFA error codes (hex on the wire)
ERR_ACCESS_DENIED, ERR_UNKNOWN_METHOD, ERR_UNKNOWN_VARIABLE, ERR_LOCAL_CONDITION = 1, 2, 3, 4
ERR_INVALID_DATA, ERR_UNKNOWN_ERROR, ERR_WRITE_DENIED, ERR_UNKNOWN_COMMAND, ERR_UNKNOWN_EVENT = 5, 6, 10, 12, 15

_HEX16 = [format(i, "X") for i in range(65536)]


class ScanSource(Protocol):
    def laser_ranges(self, angles_rad: np.ndarray) -> tuple[float, np.ndarray]: ...


class SimClockLike(Protocol):
    def now(self) -> float: ...

    async def sleep_until(self, t: float) -> None: ...


class RequestError(Exception):
    """A request the emulated scanner answers with ``sFA <code>``."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _num(token: str) -> int:
    """A CoLa A number: signed decimal with explicit sign, else hex (S32 two's complement folded)."""
    try:
        if token[:1] in "+-":
            return int(token, 10)
        value = int(token, 16)
    except ValueError:
        raise RequestError(ERR_INVALID_DATA) from None
    if not 0 <= value <= 0xFFFFFFFF:
        raise RequestError(ERR_INVALID_DATA)
    return value - 2**32 if value >= 2**31 else value


def _hex(value: int) -> str:
    return format(value & 0xFFFFFFFF, "X")


class _Client:
    """One TCP connection: its access level and whether it streams scans."""

    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.access_level = 0
        self.streaming = False
        self.dropped_scans = 0

    def send(self, payload: str) -> bool:
        """Queue one telegram; False (and nothing sent) when the client's backlog is full or it is gone."""
        transport = self.writer.transport
        if transport.is_closing() or transport.get_write_buffer_size() > MAX_CLIENT_BACKLOG_BYTES:
            return False
        self.writer.write(STX + payload.encode("latin-1") + ETX)
        return True


class Lms111Emulator:
    """A CoLa A TCP server behaving like an LMS111 (see the module docstring)."""

    def __init__(self, host: str, port: int, scan_source: ScanSource, clock: SimClockLike, *,
                 frequency_hz: float = 25, resolution_deg: float = 0.5, range_noise_m: float = 0.01,
                 max_range_m: float = 20.0, seed: int = 0, serial_number: int = 0x89A27F,
                 device_name: str = "LMS111") -> None:
        freq_raw, res_raw = round(frequency_hz * 100), round(resolution_deg * 10000)
        if self._config_status(freq_raw, res_raw) != 0:
            raise ValueError(f"LMS111 supports 25 Hz at 0.25/0.5 deg or 50 Hz at 0.5 deg, "
                             f"not {frequency_hz} Hz at {resolution_deg} deg")
        if not max_range_m > 0 or range_noise_m < 0:
            raise ValueError("max_range_m must be > 0 and range_noise_m >= 0")
        self.host = host
        self.port = port
        self.source = scan_source
        self.clock = clock
        self.range_noise_m = range_noise_m
        self.max_range_m = min(max_range_m, 65.0)
        self.serial_number = serial_number
        self.device_name = device_name
        self.rng = np.random.default_rng(seed)
        # device configuration (shared by all connections, as on the real device)
        self.frequency_raw = freq_raw  # 1/100 Hz
        self.resolution_raw = res_raw  # 1/10000 deg
        self.output_start = SCAN_AREA_START
        self.output_stop = SCAN_AREA_STOP
        self.rssi = False
        self.rssi_16bit = False
        self.name_output = False
        self.time_output = False
        self.output_interval = 1
        self.measuring = True
        # counters and state
        self.telegram_counter = 0
        self.scan_counter = 0
        self.scans_sent = 0
        self.source_failures = 0
        self.boot_s = 0.0
        self.clients: set[_Client] = set()
        self._server: asyncio.AbstractServer | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._scan_task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------ lifetime

    async def start(self) -> None:
        """Listen on (host, port); with port 0 the bound port is stored in ``self.port``."""
        self.boot_s = self.clock.now()
        self._server = await asyncio.start_server(self._serve, self.host, self.port, reuse_address=True)
        self.port = self._server.sockets[0].getsockname()[1]
        self._scan_task = asyncio.get_running_loop().create_task(self._scan_loop())
        log.info("LMS111 emulator on %s:%d (%.0f Hz, %.2f deg)", self.host, self.port, self.frequency_hz,
                 self.resolution_raw / 1e4)

    async def stop(self) -> None:
        """Stop listening, drop every connection and the scan loop."""
        if self._server is not None:
            self._server.close()
        for client in list(self.clients):
            client.writer.close()
        if self._scan_task is not None:
            self._scan_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._scan_task
        # the connection handlers end by themselves once their transport is closed (EOF)
        if self._tasks:
            _, late = await asyncio.wait(set(self._tasks), timeout=2.0)
            for t in late:
                t.cancel()
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
        self._server = None
        self._scan_task = None
        self.clients.clear()

    @property
    def frequency_hz(self) -> float:
        return self.frequency_raw / 100.0

    # ------------------------------------------------------------------ connections

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        client = _Client(writer)
        self.clients.add(client)
        buf = bytearray()
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    break
                buf += data
                while True:
                    stx = buf.find(STX)
                    if stx < 0:
                        buf.clear()
                        break
                    del buf[:stx]
                    etx = buf.find(ETX)
                    if etx < 0:
                        if len(buf) > MAX_REQUEST_BYTES:
                            buf.clear()  # an over-long request: drop it
                        break
                    request = bytes(buf[1:etx]).decode("latin-1")
                    del buf[:etx + 1]
                    if STX.decode() in request:
                        request = request.rsplit(STX.decode(), 1)[1]
                    client.send(self._answer(client, request))
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self.clients.discard(client)
            writer.close()
            if task is not None:
                self._tasks.discard(task)

    def _answer(self, client: _Client, request: str) -> str:
        tokens = request.split(" ")
        try:
            return self._dispatch(client, tokens)
        except RequestError as exc:
            return f"sFA {exc.code:X}"
        except Exception:  # e.g. the scan source failed: the device reports an error and stays up
            log.exception("LMS111 emulator: %r failed", request[:60])
            return f"sFA {ERR_UNKNOWN_ERROR:X}"

    def _dispatch(self, client: _Client, t: list[str]) -> str:
        kind = t[0]
        name = t[1] if len(t) > 1 else ""
        args = t[2:]
        if kind == "sMN":
            return self._method(client, name, args)
        if kind == "sRN":
            return self._read(name)
        if kind == "sWN":
            return self._write(client, name, args)
        if kind == "sEN":
            if name != "LMDscandata":
                raise RequestError(ERR_UNKNOWN_EVENT)
            if len(args) != 1 or args[0] not in ("0", "1"):
                raise RequestError(ERR_INVALID_DATA)
            client.streaming = args[0] == "1"
            return f"sEA LMDscandata {args[0]}"
        raise RequestError(ERR_UNKNOWN_COMMAND)

    def _need_login(self, client: _Client, code: int) -> None:
        if client.access_level < 3:
            raise RequestError(code)

    def _method(self, client: _Client, name: str, args: list[str]) -> str:
        if name == "SetAccessMode":
            if len(args) != 2:
                raise RequestError(ERR_INVALID_DATA)
            level = _num(args[0])
            ok = LOGIN_HASHES.get(level, "").upper() == args[1].upper()
            client.access_level = level if ok else 0
            return f"sAN SetAccessMode {int(ok)}"
        if name == "mLMPsetscancfg":
            self._need_login(client, ERR_ACCESS_DENIED)
            if len(args) != 5:
                raise RequestError(ERR_INVALID_DATA)
            freq, sectors, res, start, stop = (_num(a) for a in args)
            status = self._config_status(freq, res)
            if status == 0 and (sectors != 1 or start < SCAN_AREA_START or stop > SCAN_AREA_STOP or start >= stop):
                status = 4
            if status == 0:
                self.frequency_raw, self.resolution_raw = freq, res
                self.output_start, self.output_stop = SCAN_AREA_START, SCAN_AREA_STOP
            return f"sAN mLMPsetscancfg {status} {self._scancfg_fields()}"
        if name in ("LMCstartmeas", "LMCstopmeas"):
            self._need_login(client, ERR_ACCESS_DENIED)
            self.measuring = name == "LMCstartmeas"
            return f"sAN {name} 0"
        if name == "Run":
            client.access_level = 0
            return "sAN Run 1"
        if name == "mEEwriteall":
            self._need_login(client, ERR_ACCESS_DENIED)
            return "sAN mEEwriteall 1"
        raise RequestError(ERR_UNKNOWN_METHOD)

    @staticmethod
    def _config_status(freq_raw: int, res_raw: int) -> int:
        """mLMPsetscancfg status: 0 OK, 1 frequency, 2 resolution (0.25 deg only at 25 Hz)."""
        if freq_raw not in (2500, 5000):
            return 1
        if res_raw not in (2500, 5000) or (res_raw == 2500 and freq_raw != 2500):
            return 2
        return 0

    def _scancfg_fields(self) -> str:
        return f"{_hex(self.frequency_raw)} 1 {_hex(self.resolution_raw)} {_hex(SCAN_AREA_START)} " \
               f"{_hex(SCAN_AREA_STOP)}"

    def _read(self, name: str) -> str:
        if name == "LMPscancfg":
            return f"sRA LMPscancfg {self._scancfg_fields()}"
        if name == "LMPoutputRange":
            return f"sRA LMPoutputRange 1 {_hex(self.resolution_raw)} {_hex(self.output_start)} " \
                   f"{_hex(self.output_stop)}"
        if name == "STlms":
            state = STATE_READY_FOR_MEASUREMENT if self.measuring else STATE_IDLE
            return f"sRA STlms {state} 0 8 00:00:00 8 01.01.06 0 0 0"
        if name == "LMDscandata":
            if not self.measuring:
                raise RequestError(ERR_LOCAL_CONDITION)
            self.scan_counter = (self.scan_counter + 1) & 0xFFFF
            return self._scan_telegram("sRA", self._measure())
        raise RequestError(ERR_UNKNOWN_VARIABLE)

    def _write(self, client: _Client, name: str, args: list[str]) -> str:
        if name == "LMDscandatacfg":
            self._need_login(client, ERR_WRITE_DENIED)
            if len(args) != 12:
                raise RequestError(ERR_INVALID_DATA)
            v = [_num(a) for a in args]
            channel, remission, resolution, _unit, _enc1, _enc2, position, name_out, comment, time_out, interval = (
                v[0] | v[1] << 8, *v[2:])
            if channel != 1 or position or comment or interval < 1 or remission not in (0, 1) \
                    or resolution not in (0, 1):
                raise RequestError(ERR_INVALID_DATA)
            self.rssi, self.rssi_16bit = bool(remission), bool(resolution)
            self.name_output, self.time_output, self.output_interval = bool(name_out), bool(time_out), interval
            return "sWA LMDscandatacfg"
        if name == "LMPoutputRange":
            self._need_login(client, ERR_WRITE_DENIED)
            if len(args) != 4:
                raise RequestError(ERR_INVALID_DATA)
            sector, res, start, stop = (_num(a) for a in args)
            if sector != 1 or res != self.resolution_raw or not SCAN_AREA_START <= start < stop <= SCAN_AREA_STOP \
                    or (start - SCAN_AREA_START) % res or (stop - start) % res:
                raise RequestError(ERR_INVALID_DATA)
            self.output_start, self.output_stop = start, stop
            return "sWA LMPoutputRange"
        raise RequestError(ERR_UNKNOWN_VARIABLE)

    # ------------------------------------------------------------------ scans

    def beam_angles_sick_raw(self) -> np.ndarray:
        """Beam angles of the output range in SICK 1/10000 deg."""
        n = (self.output_stop - self.output_start) // self.resolution_raw + 1
        return self.output_start + self.resolution_raw * np.arange(n, dtype=np.int64)

    def _measure(self) -> tuple[float, np.ndarray]:
        """Ask the source for one scan: (stamp s, distances mm as int, 0 = no echo)."""
        angles = np.radians(self.beam_angles_sick_raw() / 1e4 - SICK_FORWARD_DEG)
        stamp, ranges = self.source.laser_ranges(angles)
        r = np.asarray(ranges, dtype=np.float64)
        if r.shape != angles.shape:
            raise ValueError(f"scan_source returned {r.shape} ranges for {angles.shape} beams")
        echo = np.isfinite(r) & (r < self.max_range_m) & (r >= 0)
        r = np.where(echo, r, 0.0)
        noisy = r + self.rng.normal(0.0, self.range_noise_m, r.shape) if self.range_noise_m else r
        mm = np.where(echo, np.clip(np.rint(noisy * 1000.0), 1, 65535), 0).astype(np.int64)
        return float(stamp), mm

    def _device_us(self, t: float) -> int:
        return int((t - self.boot_s) * 1e6) & 0xFFFFFFFF

    def _scan_telegram(self, kind: str, measured: tuple[float, np.ndarray]) -> str:
        stamp, mm = measured
        self.telegram_counter = (self.telegram_counter + 1) & 0xFFFF
        n = mm.size
        meas_raw = round(360e4 / self.resolution_raw * self.frequency_raw / 100 / 100)  # points/s in 100 Hz
        head = (f"{kind} LMDscandata 1 1 {_hex(self.serial_number)} 0 0 {_hex(self.telegram_counter)} "
                f"{_hex(self.scan_counter)} {_hex(self._device_us(stamp))} {_hex(self._device_us(self.clock.now()))} "
                f"0 0 0 0 0 {_hex(self.frequency_raw)} {_hex(meas_raw)} 0")
        block_head = f"3F800000 00000000 {_hex(self.output_start)} {_hex(self.resolution_raw)} {_hex(n)}"
        dist = f"DIST1 {block_head} " + " ".join([_HEX16[v] for v in mm.tolist()])
        parts = [head]
        rssi_block = ""
        if self.rssi:
            rssi = self._remission(mm)
            rssi_block = f"RSSI1 {block_head} " + " ".join([_HEX16[v] for v in rssi.tolist()])
        if self.rssi and self.rssi_16bit:
            parts += ["2", dist, rssi_block, "0"]
        elif self.rssi:
            parts += ["1", dist, "1", rssi_block]
        else:
            parts += ["1", dist, "0"]
        parts.append("0")  # no position block
        parts.append(f"1 {_hex(len(self.device_name))} {self.device_name}" if self.name_output else "0")
        parts.append("0")  # no comment
        if self.time_output:
            when = datetime.datetime.fromtimestamp(max(stamp, 0.0), tz=datetime.UTC)
            parts.append(f"1 {_hex(when.year)} {_hex(when.month)} {_hex(when.day)} {_hex(when.hour)} "
                         f"{_hex(when.minute)} {_hex(when.second)} {_hex(when.microsecond)}")
        else:
            parts.append("0")
        parts.append("0")  # no event block
        return " ".join(parts)

    def _remission(self, mm: np.ndarray) -> np.ndarray:
        """Synthetic remission: falls with distance, 0 without echo (8- or 16-bit per LMDscandatacfg)."""
        full = 65535 if self.rssi_16bit else 255
        value = np.rint(full * 0.9 / (1.0 + mm / 5000.0)).astype(np.int64)
        return np.where(mm > 0, np.maximum(value, 1), 0)

    async def _scan_loop(self) -> None:
        """One scan per period on ``clock``: t_k = anchor + k / f (no drift); a late loop re-anchors at now."""
        period = 1.0 / self.frequency_hz
        anchor, k = self.clock.now(), 1
        skipped = 0
        while True:
            await self.clock.sleep_until(anchor + k * period)
            k += 1
            now = self.clock.now()
            if 1.0 / self.frequency_hz != period or now > anchor + k * period:
                period = 1.0 / self.frequency_hz  # changed by mLMPsetscancfg, or we fell behind
                anchor, k = now, 1
            if not self.measuring:
                continue
            self.scan_counter = (self.scan_counter + 1) & 0xFFFF
            skipped += 1
            if skipped < self.output_interval:
                continue
            skipped = 0
            streaming = [c for c in self.clients if c.streaming]
            if not streaming:
                continue
            try:
                telegram = self._scan_telegram("sSN", self._measure())
            except Exception:
                self.source_failures += 1
                if self.source_failures % 250 == 1:  # rate-limited: a broken source must not flood the log
                    log.exception("LMS111 emulator: scan source failed (%d times)", self.source_failures)
                continue
            for client in streaming:
                if client.send(telegram):
                    self.scans_sent += 1
                else:
                    client.dropped_scans += 1
