"""SICK CoLa A framing, tokens and command encoding (protocols.md §3.1, §3.2). Pure, I/O-free.

A CoLa A telegram is ``STX`` (0x02) + ASCII tokens separated by single spaces + ``ETX`` (0x03); there is no length
and no checksum. Numbers are hex without leading zeros (negative S32 as two's complement, ``FFF92230`` = -450000),
or signed decimal with an explicit sign (``+5000``); strings are ``<len> <chars>``.

``FrameParser`` cuts a TCP byte stream into telegram payloads: telegrams split across reads, several in one read,
bytes outside STX..ETX and over-long telegrams (the buffer is bounded) are all handled; every problem is reported as
a ``FramingError`` item in the output, never raised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STX = 0x02
ETX = 0x03
STX_BYTE = b"\x02"
ETX_BYTE = b"\x03"

#: telegram payloads longer than this are discarded (a 1081-point DIST1+RSSI1 scan is ~12 KiB)
DEFAULT_MAX_TELEGRAM_BYTES = 64 * 1024

#: ``sFA <code>`` meanings (numbering from sick_scan_xd SopasBase)
SFA_ERRORS: dict[int, str] = {
    1: "method access denied",
    2: "unknown method",
    3: "unknown variable",
    4: "local condition failed",
    5: "invalid data",
    6: "unknown error",
    7: "buffer overflow",
    8: "buffer underflow",
    9: "unknown type",
    10: "variable write access denied",
    11: "unknown cmd for nameserver",
    12: "unknown CoLa command",
    13: "method server busy",
    14: "flex out of bounds",
    15: "unknown event index",
    16: "CoLa A value overflow",
    17: "CoLa A invalid character",
}


class ColaError(ValueError):
    """A telegram that does not follow CoLa A / the expected layout; the message names the field and the token."""


class FramingError(ColaError):
    """A problem in the byte stream (bytes outside STX..ETX, an interrupted or over-long telegram)."""


class DeviceError(ColaError):
    """The scanner answered ``sFA <code>``: it refused or did not understand a request."""

    def __init__(self, code: int, request: str = "") -> None:
        self.code = code
        self.request = request
        meaning = SFA_ERRORS.get(code, "unknown error code")
        where = f" to {request!r}" if request else ""
        super().__init__(f"scanner replied sFA {code:X}{where}: {meaning}")


# --------------------------------------------------------------------------- framing


class FrameParser:
    """Incremental STX..ETX splitter with a bounded buffer.

    ``feed(data)`` returns, in stream order, each complete telegram payload (bytes without STX/ETX) and a
    ``FramingError`` for each problem: bytes outside a telegram (skipped), a telegram interrupted by a new STX
    (dropped) or longer than ``max_telegram_bytes`` (dropped; the parser resynchronises at the next STX).
    Memory held between calls is at most ``max_telegram_bytes``.
    """

    def __init__(self, max_telegram_bytes: int = DEFAULT_MAX_TELEGRAM_BYTES) -> None:
        if max_telegram_bytes < 1:
            raise ValueError(f"max_telegram_bytes must be >= 1, got {max_telegram_bytes}")
        self.max_telegram_bytes = max_telegram_bytes
        self._buf = bytearray()  # payload bytes of the telegram being received
        self._in_telegram = False
        self._skipping = False  # inside an over-long telegram: drop until the next STX
        self.telegrams = 0
        self.errors = 0

    @property
    def buffered(self) -> int:
        """Bytes currently held (a partial telegram)."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget any partial telegram (after a reconnect)."""
        self._buf.clear()
        self._in_telegram = False
        self._skipping = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes | FramingError]:
        out: list[bytes | FramingError] = []
        data = bytes(data)
        pos, n = 0, len(data)
        while pos < n:
            if self._skipping:
                stx = data.find(STX_BYTE, pos)
                if stx < 0:
                    return out
                self._skipping = False
                pos = stx
            if not self._in_telegram:
                stx = data.find(STX_BYTE, pos)
                junk_end = n if stx < 0 else stx
                if junk_end > pos:
                    self._error(out, f"{junk_end - pos} byte(s) outside STX..ETX skipped")
                if stx < 0:
                    return out
                self._in_telegram = True
                pos = stx + 1
                continue
            etx = data.find(ETX_BYTE, pos)
            stx = data.find(STX_BYTE, pos)
            if stx >= 0 and (etx < 0 or stx < etx):
                self._error(out, f"telegram interrupted by STX after {len(self._buf) + stx - pos} byte(s); dropped")
                self._buf.clear()
                pos = stx + 1
                continue
            end = n if etx < 0 else etx
            if len(self._buf) + end - pos > self.max_telegram_bytes:
                self._error(out, f"telegram longer than {self.max_telegram_bytes} bytes without ETX; dropped")
                self._buf.clear()
                self._in_telegram = False
                self._skipping = True
                pos = end
                continue
            self._buf += data[pos:end]
            if etx < 0:
                return out
            out.append(bytes(self._buf))
            self.telegrams += 1
            self._buf.clear()
            self._in_telegram = False
            pos = etx + 1
        return out

    def _error(self, out: list[bytes | FramingError], text: str) -> None:
        self.errors += 1
        out.append(FramingError(text))


def frame(payload: str | bytes) -> bytes:
    """Wrap a telegram payload in STX..ETX; rejects payloads that contain STX or ETX themselves."""
    body = payload.encode("ascii") if isinstance(payload, str) else bytes(payload)
    if STX_BYTE in body or ETX_BYTE in body:
        raise ColaError(f"payload {body[:40]!r} contains STX or ETX")
    return STX_BYTE + body + ETX_BYTE


# --------------------------------------------------------------------------- numbers and tokens

_HEX_DIGITS = b"0123456789ABCDEFabcdef"
#: byte -> nibble value, 255 for anything that is not a hex digit
HEX_LUT = np.full(256, 255, dtype=np.uint8)
for _i, _c in enumerate(b"0123456789ABCDEF"):
    HEX_LUT[_c] = _i
for _i, _c in enumerate(b"abcdef"):
    HEX_LUT[_c] = 10 + _i


def parse_uint(token: bytes, field: str, max_digits: int = 8) -> int:
    """An unsigned CoLa A number: hex (``1388``) or decimal with an explicit ``+`` (``+5000``)."""
    if token[:1] == b"+" and token[1:].isdigit() and len(token) <= 11:
        return int(token[1:])
    if not token or len(token) > max_digits or token.strip(_HEX_DIGITS):
        raise ColaError(f"{field}: {token[:24]!r} is not a hex number of at most {max_digits} digits")
    return int(token, 16)


def parse_int32(token: bytes, field: str) -> int:
    """A signed 32-bit number: two's complement hex (``FFF92230`` = -450000) or signed decimal (``-450000``)."""
    if token[:1] in (b"+", b"-") and token[1:].isdigit() and len(token) <= 11:
        value = int(token)
        if not -(2**31) <= value < 2**31:
            raise ColaError(f"{field}: {token!r} is out of the S32 range")
        return value
    value = parse_uint(token, field)
    return value - 2**32 if value >= 2**31 else value


def parse_real32(token: bytes, field: str) -> float:
    """An IEEE-754 single sent as 8 hex digits (``3F800000`` = 1.0)."""
    if len(token) != 8 or token.strip(_HEX_DIGITS):
        raise ColaError(f"{field}: {token[:24]!r} is not a REAL32 as 8 hex digits")
    return float(np.frombuffer(bytes.fromhex(token.decode("ascii")), dtype=">f4")[0])


def hex_u(value: int) -> str:
    """An unsigned number as CoLa A hex (upper case, no leading zeros)."""
    return format(value, "X")


def hex_s32(value: int) -> str:
    """A signed 32-bit number as two's complement hex."""
    return format(value & 0xFFFFFFFF, "X")


class Tokens:
    """The space-separated tokens of one payload, with their byte offsets for vectorised number decoding."""

    __slots__ = ("payload", "arr", "starts", "ends", "count", "_head")

    #: the first tokens are also kept as a plain list (header fields are read one by one)
    HEAD = 32

    def __init__(self, payload: bytes) -> None:
        self.payload = payload
        self.arr = np.frombuffer(payload, dtype=np.uint8)
        spaces = np.flatnonzero(self.arr == 0x20)
        self.starts = np.empty(len(spaces) + 1, dtype=np.int64)
        self.starts[0] = 0
        self.starts[1:] = spaces + 1
        self.ends = np.empty(len(spaces) + 1, dtype=np.int64)
        self.ends[:-1] = spaces
        self.ends[-1] = len(payload)
        self.count = len(self.starts)
        self._head: list[bytes] | None = None

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i: int) -> bytes:
        if not 0 <= i < self.count:
            raise ColaError(f"telegram ends after {self.count} tokens; token {i} is missing")
        if i < self.HEAD:
            if self._head is None:
                self._head = self.payload.split(b" ", self.HEAD)  # element HEAD (if any) is the remainder
            return self._head[i]
        return self.payload[self.starts[i]:self.ends[i]]

    def hex_array(self, first: int, count: int, field: str, max_digits: int = 4) -> np.ndarray:
        """Tokens ``first .. first+count-1`` as unsigned hex numbers (int64), decoded without a Python loop."""
        if count == 0:
            return np.zeros(0, dtype=np.int64)
        last = first + count - 1
        if first < 0 or last >= self.count:
            raise ColaError(f"{field}: expected {count} values from token {first}, the telegram has {self.count}")
        lengths = self.ends[first:last + 1] - self.starts[first:last + 1]
        if lengths.min() < 1 or lengths.max() > max_digits:
            bad = int(np.flatnonzero((lengths < 1) | (lengths > max_digits))[0])
            raise ColaError(f"{field}: value {bad} {self[first + bad][:24]!r} is not 1..{max_digits} hex digits")
        # right-align every token in a (count, max_digits) grid of nibbles, then weigh the columns by 16**k
        idx = self.ends[first:last + 1, None] + _COLUMNS[max_digits]
        valid = idx >= self.starts[first:last + 1, None]
        nib = HEX_LUT[self.arr[np.where(valid, idx, 0)]]
        nib[~valid] = 0
        if (nib == 255).any():
            row = int(np.flatnonzero((nib == 255).any(axis=1))[0])
            raise ColaError(f"{field}: value {row} {self[first + row][:24]!r} is not a hex number")
        return nib.astype(np.int64) @ _WEIGHTS[max_digits]


_COLUMNS = {d: np.arange(-d, 0, dtype=np.int64) for d in range(1, 9)}  # offsets from a token's end
_WEIGHTS = {d: 16 ** np.arange(d - 1, -1, -1, dtype=np.int64) for d in range(1, 9)}


# --------------------------------------------------------------------------- replies


@dataclass(frozen=True)
class Reply:
    """A decoded telegram's head: ``kind`` (``sRA``, ``sAN``, ``sSN``, ``sFA`` ...), ``name`` and its tokens."""

    kind: str
    name: str
    tokens: Tokens


def parse_reply(payload: bytes) -> Reply:
    """Split a payload into its command type, name and tokens; raises ColaError when it is not CoLa A."""
    if not payload:
        raise ColaError("empty telegram")
    tokens = Tokens(payload)
    kind = tokens[0]
    if len(kind) != 3 or not kind.isalpha() or not kind.isascii():
        raise ColaError(f"telegram starts with {kind[:24]!r}, not a CoLa A command type (sRA, sAN, sSN, sFA ...)")
    kind_s = kind.decode("ascii")
    if kind_s == "sFA":
        return Reply(kind_s, "", tokens)
    name = tokens[1] if tokens.count > 1 else b""
    if not name.isascii() or not name.replace(b"_", b"").isalnum():
        raise ColaError(f"{kind_s}: command name {name[:24]!r} is not an ASCII identifier")
    return Reply(kind_s, name.decode("ascii"), tokens)


def check_not_error(reply: Reply, request: str = "") -> None:
    """Raise DeviceError for an ``sFA <code>`` reply."""
    if reply.kind == "sFA":
        code = parse_uint(reply.tokens[1], "sFA error code") if reply.tokens.count > 1 else 6
        raise DeviceError(code, request)


# --------------------------------------------------------------------------- commands (client -> scanner)


def cmd_login(level: int = 3, password_hash: str = "F4724744") -> bytes:
    """``sMN SetAccessMode 03 F4724744``: log in (3 authorized client, 4 service) with the password's hash."""
    return frame(f"sMN SetAccessMode {level:02d} {password_hash}")


def cmd_read(variable: str) -> bytes:
    """``sRN <variable>`` (e.g. LMPscancfg, STlms, LMDscandata)."""
    return frame(f"sRN {variable}")


def cmd_method(method: str, *args: str) -> bytes:
    """``sMN <method> [args]`` (e.g. LMCstartmeas, Run)."""
    return frame(" ".join(("sMN", method, *args)))


def cmd_set_scan_config(frequency_hz: float, resolution_deg: float, start_deg: float = -45.0,
                        stop_deg: float = 225.0) -> bytes:
    """``sMN mLMPsetscancfg +<freq 1/100 Hz> +1 +<res 1/10000 deg> <start> <stop>`` (signed decimal form)."""
    freq = round(frequency_hz * 100)
    res = round(resolution_deg * 10000)
    start = round(start_deg * 10000)
    stop = round(stop_deg * 10000)
    return frame(f"sMN mLMPsetscancfg {freq:+d} +1 {res:+d} {start:+d} {stop:+d}")


def cmd_scandata_config(*, intensities: bool, rssi_16bit: bool = True, device_name: bool = False,
                        time_info: bool = False, output_interval: int = 1) -> bytes:
    """``sWN LMDscandatacfg``: channel DIST1, remission on/off and 8/16-bit, no encoder/position/comment."""
    return frame(
        f"sWN LMDscandatacfg 01 00 {int(intensities)} {int(rssi_16bit)} 0 00 00 0 {int(device_name)} 0 "
        f"{int(time_info)} +{output_interval}"
    )


def cmd_stream(on: bool) -> bytes:
    """``sEN LMDscandata 1|0``: start or stop streaming each scan as ``sSN LMDscandata``."""
    return frame(f"sEN LMDscandata {int(on)}")
