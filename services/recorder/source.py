"""Reading any bag as zagv messages: zagv recordings, ROS 2 bags (MCAP or sqlite3) and ROS 1 bags (``rosbags``).

``BagSource(paths).messages()`` yields ``(log_time_ns, topic_name, message)`` in log-time order. A topic whose type
has no zagv counterpart, or a message that does not deserialize, is reported once per topic in ``problems`` (with a
count in ``skipped``) and skipped; reading goes on.
"""

from __future__ import annotations

import collections
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader

from services.recorder.rosconv import STANDARD_TYPES, ZAGV_MESSAGE_TYPE, RosDecoder, UnsupportedMessage, make_typestore

#: ROS types the decoder understands (on any topic name)
DECODABLE = {*STANDARD_TYPES.values(), ZAGV_MESSAGE_TYPE, "tf2_msgs/msg/TFMessage"}


def bag_paths(path: str | Path) -> list[Path]:
    """The bag(s) at ``path``: a ROS 1 ``.bag`` file, a rosbag2 folder, or a folder of split rosbag2 folders."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no bag at {p}")
    if p.is_file() or (p / "metadata.yaml").is_file():
        return [p]
    parts = sorted(d for d in p.iterdir() if (d / "metadata.yaml").is_file())
    if not parts:
        raise FileNotFoundError(f"{p}: neither a ROS 1 .bag file nor a rosbag2 folder (metadata.yaml)")
    return parts


class BagSource:
    """zagv messages of one or more bags, in log-time order."""

    def __init__(self, path: str | Path) -> None:
        self.paths = bag_paths(path)
        self.problems: dict[str, str] = {}
        self.skipped: collections.Counter[str] = collections.Counter()
        self.decoder = RosDecoder()
        self._reader = AnyReader(self.paths, default_typestore=make_typestore())

    def __enter__(self) -> BagSource:
        self._reader.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._reader.close()

    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    @property
    def end_ns(self) -> int:
        return int(self._reader.end_time)

    @property
    def topics(self) -> dict[str, str]:
        """Bag topic -> message type."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    def _skip(self, topic: str, reason: str) -> None:
        self.skipped[topic] += 1
        self.problems.setdefault(topic, reason)

    def messages(self, start_ns: int | None = None, end_ns: int | None = None,
                 names: set[str] | None = None) -> Iterator[tuple[int, str, Any]]:
        """``(log_time_ns, zagv topic name, message)``, only of the topic ``names`` when given (other bag topics
        are not even deserialized); static transforms (``/tf_static``, the laser mount) are always applied, also
        those before ``start_ns``."""
        conns = []
        for c in self._reader.connections:
            if names is not None and c.topic != "/tf_static" and c.topic.lstrip("/") not in names and not (
                    c.topic == "/tf" and "tf/map_odom" in names):
                continue
            if c.msgtype in DECODABLE:
                conns.append(c)
            else:
                self.problems.setdefault(c.topic, f"type {c.msgtype} has no zagv counterpart")
                self.skipped[c.topic] += c.msgcount
        for conn, t_ns, raw in self._reader.messages(connections=conns):
            if end_ns is not None and t_ns > end_ns:
                break
            before = start_ns is not None and t_ns < start_ns
            if before and conn.topic != "/tf_static":
                continue
            try:
                ros_msg = self._reader.deserialize(raw, conn.msgtype)
                items = self.decoder.decode(conn.topic, conn.msgtype, ros_msg)
            except UnsupportedMessage as exc:
                self._skip(conn.topic, str(exc))
                continue
            except Exception as exc:  # a malformed message: named and skipped, the replay goes on
                self._skip(conn.topic, f"malformed {conn.msgtype}: {type(exc).__name__}: {exc}")
                continue
            if before:
                continue
            for name, msg in items:
                yield t_ns, name, msg
