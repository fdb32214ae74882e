"""The CoLa A conversation over one TCP connection (asyncio streams): requests, replies and the scan stream."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import time

from services.lidar.cola import ColaError, FrameParser, FramingError, Reply, check_not_error, parse_reply

#: request command type -> the reply's command type
REPLY_KIND = {"sRN": "sRA", "sWN": "sWA", "sMN": "sAN", "sEN": "sEA"}


class LinkLost(ConnectionError):
    """The scanner closed the connection or stopped answering."""


class ColaLink:
    """Requests with matching replies, then ``next_reply`` for streamed telegrams.

    Framing problems and undecodable telegrams are counted (``framing_errors``, ``bad_telegrams``) and remembered
    in ``last_error``; they never end the conversation.
    """

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, reply_timeout_s: float,
                 max_telegram_bytes: int) -> None:
        self.reader = reader
        self.writer = writer
        self.reply_timeout_s = reply_timeout_s
        self.parser = FrameParser(max_telegram_bytes)
        self._pending: collections.deque[bytes | FramingError] = collections.deque()
        self.framing_errors = 0
        self.bad_telegrams = 0
        self.last_error = ""

    @classmethod
    async def connect(cls, host: str, port: int, *, connect_timeout_s: float, reply_timeout_s: float,
                      max_telegram_bytes: int) -> ColaLink:
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), connect_timeout_s)
        except TimeoutError:
            raise LinkLost(f"no TCP connection to {host}:{port} within {connect_timeout_s} s") from None
        except OSError as exc:
            raise LinkLost(f"cannot connect to {host}:{port}: {exc.strerror or exc}") from None
        return cls(reader, writer, reply_timeout_s=reply_timeout_s, max_telegram_bytes=max_telegram_bytes)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.writer.close()

    async def send(self, telegram: bytes) -> None:
        try:
            self.writer.write(telegram)
            await self.writer.drain()
        except (ConnectionError, OSError) as exc:
            raise LinkLost(f"sending failed: {exc}") from None

    async def _read_more(self, timeout_s: float) -> bool:
        """Read once and frame the bytes; False on timeout; LinkLost on EOF (wall-time timeout: link health)."""
        try:
            data = await asyncio.wait_for(self.reader.read(65536), timeout_s)
        except TimeoutError:
            return False
        except (ConnectionError, OSError) as exc:
            raise LinkLost(f"connection lost: {exc}") from None
        if not data:
            raise LinkLost("the scanner closed the connection")
        self._pending.extend(self.parser.feed(data))
        return True

    async def next_reply(self, timeout_s: float) -> Reply | None:
        """The next decodable telegram's head, or None after ``timeout_s`` (wall time) without one."""
        deadline = time.monotonic() + timeout_s
        while True:
            while self._pending:
                item = self._pending.popleft()
                if isinstance(item, FramingError):
                    self.framing_errors += 1
                    self.last_error = str(item)
                    continue
                try:
                    return parse_reply(item)
                except ColaError as exc:
                    self.bad_telegrams += 1
                    self.last_error = str(exc)
            left = deadline - time.monotonic()
            if left <= 0 or not await self._read_more(left):
                return None

    async def request(self, telegram: bytes) -> Reply:
        """Send one request and return its reply (``sFA`` raises DeviceError); other telegrams are skipped."""
        text = telegram[1:-1].decode("ascii", "replace")
        kind, _, rest = text.partition(" ")
        name = rest.split(" ", 1)[0]
        want = REPLY_KIND.get(kind)
        await self.send(telegram)
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            reply = await self.next_reply(max(deadline - time.monotonic(), 0.0))
            if reply is None:
                raise LinkLost(f"no reply to {text!r} within {self.reply_timeout_s} s")
            if reply.kind == "sFA":
                check_not_error(reply, text)
            if reply.kind == want and reply.name == name:
                return reply
            if reply.kind == "sMA" and reply.name == name:
                continue  # method accepted; the sAN follows
