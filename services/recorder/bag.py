"""Writing zagv messages as rosbag2 folders with MCAP storage (``rosbags``), split by size or duration.

A recording is the bag folder ``<out>/`` itself, or when split, a folder of bags ``<out>/<name>_0000/``,
``<out>/<name>_0001/``, ... Each bag is a standard rosbag2 folder (``metadata.yaml`` + one ``.mcap``) that ROS 2
tools, Foxglove, ``rosbags`` and the ``mcap`` readers open on their own. Message log times are nanoseconds on the
robot's clock (sim time when the simulator runs). ``metadata.yaml`` custom data holds the robot id and the JSON
Schema of every message carried as ``zagv_msgs/msg/Message``.
"""

from __future__ import annotations

import collections
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgspec
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys.store import Typestore

from proto import messages as m
from services.recorder.rosconv import ZAGV_MESSAGE_TYPE, RosEncoder, make_typestore

ROSBAG2_VERSION: Literal[8, 9] = 8


@dataclass
class RecordStats:
    """Running totals of a recording: messages, CDR bytes written, and per-topic counts."""

    messages: int = 0
    bytes: int = 0
    first_ns: int | None = None
    last_ns: int = 0
    per_topic: collections.Counter[str] = field(default_factory=collections.Counter)
    bags: list[Path] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return 0.0 if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9

    def line(self) -> str:
        """One progress line: messages, MB, rate over the recorded (clock) time."""
        rate = self.messages / self.duration_s if self.duration_s > 0 else 0.0
        return (f"{self.messages} msgs  {self.bytes / 1e6:.2f} MB  {self.duration_s:.1f} s  {rate:.0f} msg/s  "
                f"{len(self.bags)} bag(s)")


class BagRecorder:
    """Writes zagv messages (by topic name) to rosbag2/MCAP bags; opens a new bag past ``split_bytes`` of messages
    or ``split_duration_s`` of log time (0: no split)."""

    def __init__(self, out: Path, *, robot_id: str = "r1", split_bytes: int = 0, split_duration_s: float = 0.0,
                 store: Typestore | None = None) -> None:
        self.out = Path(out)
        if self.out.exists():
            raise FileExistsError(f"{self.out} exists already; a recording never overwrites")
        self.robot_id = robot_id
        self.split_bytes = split_bytes
        self.split_duration_ns = int(split_duration_s * 1e9)
        self.store = store or make_typestore()
        self.encoder = RosEncoder(self.store)
        self.stats = RecordStats()
        self._writer: Writer | None = None
        self._connections: dict[tuple[str, str], Any] = {}
        self._bag_bytes = 0
        self._bag_start_ns = 0
        self._index = 0
        self._zagv_types: set[str] = set()
        self._static: dict[str, tuple[str, str, Any]] = {}

    # ------------------------------------------------------------------ bags
    def _bag_path(self, index: int) -> Path:
        return self.out / f"{self.out.name}_{index:04d}"

    def _open(self, log_time_ns: int) -> Writer:
        if self.split_bytes or self.split_duration_ns:
            path = self._bag_path(self._index)
        else:
            path = self.out
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = Writer(path, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
        writer.set_custom_data("zagv.robot_id", self.robot_id)
        writer.open()
        self._writer = writer
        self._connections = {}
        self._zagv_types = set()
        self._bag_bytes = 0
        self._bag_start_ns = log_time_ns
        self._index += 1
        self.stats.bags.append(path)
        # every bag opens on its own: repeat the static transforms in it
        for topic, kind, msg in list(self._static.values()):
            self._write(topic, kind, msg, log_time_ns, count=False)
        return writer

    def _close_bag(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _connection(self, topic: str, kind: str) -> Any:
        assert self._writer is not None
        conn = self._connections.get((topic, kind))
        if conn is None:
            conn = self._writer.add_connection(topic, kind, typestore=self.store)
            self._connections[(topic, kind)] = conn
        return conn

    def _write(self, topic: str, kind: str, ros_msg: Any, log_time_ns: int, *, count: bool = True) -> None:
        assert self._writer is not None
        data = self.store.serialize_cdr(ros_msg, kind)
        if kind == ZAGV_MESSAGE_TYPE and ros_msg.type_name not in self._zagv_types:
            self._zagv_types.add(ros_msg.type_name)
            t = getattr(m, ros_msg.type_name)
            self._writer.set_custom_data(f"zagv.schema.{ros_msg.type_name}",
                                         json.dumps(msgspec.json.schema(t), separators=(",", ":")))
        self._writer.write(self._connection(topic, kind), log_time_ns, data)
        self._bag_bytes += len(data)
        if count:
            s = self.stats
            s.messages += 1
            s.bytes += len(data)
            s.per_topic[topic] += 1
            s.first_ns = log_time_ns if s.first_ns is None else min(s.first_ns, log_time_ns)
            s.last_ns = max(s.last_ns, log_time_ns)

    # ------------------------------------------------------------------ public
    def write(self, name: str, msg: m.Message, log_time_ns: int) -> None:
        """Record one zagv message of topic ``name`` (short name, e.g. ``scan``) at ``log_time_ns``."""
        if self._writer is None:
            self._open(log_time_ns)
        elif (self.split_bytes and self._bag_bytes >= self.split_bytes) or (
                self.split_duration_ns and log_time_ns - self._bag_start_ns >= self.split_duration_ns):
            self._close_bag()
            self._open(log_time_ns)
        for topic, kind, ros_msg in self.encoder.encode(name, msg):
            if topic == "/tf_static":
                for tf in ros_msg.transforms:
                    self._static[tf.child_frame_id] = (topic, kind, ros_msg)
            self._write(topic, kind, ros_msg, log_time_ns)

    def close(self) -> list[Path]:
        """Finish the current bag (writes its metadata.yaml); returns every bag written."""
        self._close_bag()
        return list(self.stats.bags)

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
