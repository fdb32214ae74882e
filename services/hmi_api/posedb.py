"""The pose database (the paper's §4.2): named goal poses in the map frame, in a user-defined order.

SQLite in WAL mode with ``synchronous=FULL``: every commit fsyncs the write-ahead log before ``commit()``
returns, so a pose whose write was acknowledged survives a kill -9 of the service and also an OS crash or power
loss. (``NORMAL`` with WAL would survive a process kill too, but could lose the last commits on power loss; pose
writes are rare, so the extra fsync costs nothing that matters.) Every change is one transaction
(``BEGIN IMMEDIATE`` .. ``COMMIT``); the API acknowledges a write only after its commit.

Schema versions live in ``PRAGMA user_version``; ``MIGRATIONS[i]`` brings a database from version i to i+1, in
the same transaction as the version bump. A database newer than this code is refused, not touched.
Ordering: ``position`` (integer, ascending); move up/down swaps positions with the neighbour.
"""

from __future__ import annotations

import builtins
import contextlib
import math
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec

from services.common.se2 import wrap_angle

DB_FILE = "poses.sqlite3"
EXPORT_FORMAT = "zagv-poses"
EXPORT_VERSION = 1
NAME_MAX = 100
COORD_LIMIT_M = 1e6

MIGRATIONS: list[str] = [
    # 0 -> 1: the pose table and its ordering index
    """
    CREATE TABLE poses (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        name TEXT NOT NULL,
        x_m REAL NOT NULL,
        y_m REAL NOT NULL,
        theta_rad REAL NOT NULL,
        position INTEGER NOT NULL,
        created_at REAL NOT NULL,
        updated_at REAL NOT NULL
    );
    CREATE INDEX poses_by_position ON poses(position, id);
    """,
]
SCHEMA_VERSION = len(MIGRATIONS)


class PoseRecord(msgspec.Struct):
    """A stored pose: map-frame x, y (m) and theta (rad); ``index`` is its 1-based place in the list."""

    id: int
    name: str
    x: float
    y: float
    theta: float
    index: int
    created_at: float
    updated_at: float


class PoseDbError(ValueError):
    """A request the database refuses (bad value, unknown id); the message says why."""


class PoseNotFound(PoseDbError):
    pass


class PoseListFull(PoseDbError):
    """The pose list holds ``max_poses`` already."""


def check_pose(name: str, x: float, y: float, theta: float) -> tuple[str, float, float, float]:
    """Validate and normalise a pose; raises PoseDbError naming the bad field."""
    name = name.strip()
    if not name:
        raise PoseDbError("name must not be empty")
    if len(name) > NAME_MAX:
        raise PoseDbError(f"name is longer than {NAME_MAX} characters")
    if any(ch < " " or ch == "\x7f" for ch in name):
        raise PoseDbError("name must not contain control characters (newline, tab, ...)")
    for field_name, v in (("x", x), ("y", y), ("theta", theta)):
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            raise PoseDbError(f"{field_name} must be a finite number, got {v!r}")
    for field_name, v in (("x", x), ("y", y)):
        if abs(v) > COORD_LIMIT_M:
            raise PoseDbError(f"{field_name} must be within ±{COORD_LIMIT_M:g} m, got {v}")
    return name, float(x), float(y), wrap_angle(float(theta))


def check_id(pose_id: int) -> int:
    """An id SQLite can hold (a 64-bit signed integer); anything else names no pose."""
    if not 0 < pose_id < 2**63:
        raise PoseNotFound(f"no pose with id {pose_id}")
    return pose_id


class PoseDb:
    """One SQLite connection (use it from one thread at a time)."""

    def __init__(self, path: str | Path, *, max_poses: int = 1000) -> None:
        self.path = Path(path)
        self.max_poses = max_poses
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=10.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self.migrate()

    def close(self) -> None:
        self._db.close()

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    @property
    def version(self) -> int:
        return int(self._db.execute("PRAGMA user_version").fetchone()[0])

    def migrate(self) -> int:
        """Apply pending migrations; returns the resulting schema version."""
        with self._tx() as db:
            current = int(db.execute("PRAGMA user_version").fetchone()[0])
            if current > SCHEMA_VERSION:
                raise PoseDbError(f"{self.path}: schema version {current} is newer than this software "
                                  f"({SCHEMA_VERSION}); refusing to touch it")
            for version in range(current, SCHEMA_VERSION):
                for statement in MIGRATIONS[version].split(";"):
                    if statement.strip():
                        db.execute(statement)
                db.execute(f"PRAGMA user_version = {version + 1}")
        return self.version

    # ------------------------------------------------------------------ reads

    def list(self) -> list[PoseRecord]:
        rows = self._db.execute(
            "SELECT id, name, x_m, y_m, theta_rad, created_at, updated_at FROM poses ORDER BY position, id"
        ).fetchall()
        return [PoseRecord(id=r[0], name=r[1], x=r[2], y=r[3], theta=r[4], index=i + 1, created_at=r[5],
                           updated_at=r[6]) for i, r in enumerate(rows)]

    def get(self, pose_id: int) -> PoseRecord:
        check_id(pose_id)
        for p in self.list():
            if p.id == pose_id:
                return p
        raise PoseNotFound(f"no pose with id {pose_id}")

    # ------------------------------------------------------------------ writes (each one transaction)

    def _check_room(self, db: sqlite3.Connection, adding: int) -> None:
        held = db.execute("SELECT COUNT(*) FROM poses").fetchone()[0]
        if held + adding > self.max_poses:
            raise PoseListFull(f"the pose list holds {held} poses; {adding} more would pass the limit of "
                               f"{self.max_poses}")

    def add(self, name: str, x: float, y: float, theta: float) -> PoseRecord:
        name, x, y, theta = check_pose(name, x, y, theta)
        now = time.time()
        with self._tx() as db:
            self._check_room(db, 1)
            position = db.execute("SELECT COALESCE(MAX(position), 0) + 1 FROM poses").fetchone()[0]
            cur = db.execute(
                "INSERT INTO poses (name, x_m, y_m, theta_rad, position, created_at, updated_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)", (name, x, y, theta, position, now, now))
            assert cur.lastrowid is not None  # an INSERT sets it
            new_id = cur.lastrowid
        return self.get(new_id)

    def update(self, pose_id: int, *, name: str | None = None, x: float | None = None, y: float | None = None,
               theta: float | None = None) -> PoseRecord:
        check_id(pose_id)
        with self._tx() as db:
            row = db.execute("SELECT name, x_m, y_m, theta_rad FROM poses WHERE id = ?", (pose_id,)).fetchone()
            if row is None:
                raise PoseNotFound(f"no pose with id {pose_id}")
            merged = check_pose(row[0] if name is None else name, row[1] if x is None else x,
                                row[2] if y is None else y, row[3] if theta is None else theta)
            db.execute("UPDATE poses SET name = ?, x_m = ?, y_m = ?, theta_rad = ?, updated_at = ? WHERE id = ?",
                       (*merged, time.time(), pose_id))
        return self.get(pose_id)

    def delete(self, pose_id: int) -> None:
        check_id(pose_id)
        with self._tx() as db:
            if db.execute("DELETE FROM poses WHERE id = ?", (pose_id,)).rowcount == 0:
                raise PoseNotFound(f"no pose with id {pose_id}")

    def move(self, pose_id: int, direction: str) -> builtins.list[PoseRecord]:
        """Swap the pose with its neighbour above ("up", towards the start) or below ("down").

        Moving the first pose up or the last one down leaves the order as it is.
        """
        if direction not in ("up", "down"):
            raise PoseDbError(f"direction must be 'up' or 'down', got {direction!r}")
        with self._tx() as db:
            ordered = [r[0] for r in db.execute("SELECT id FROM poses ORDER BY position, id")]
            if pose_id not in ordered:
                raise PoseNotFound(f"no pose with id {pose_id}")
            i = ordered.index(pose_id)
            j = i - 1 if direction == "up" else i + 1
            if 0 <= j < len(ordered):
                ordered[i], ordered[j] = ordered[j], ordered[i]
                # renumber densely: positions become 1..n in the new order
                db.executemany("UPDATE poses SET position = ? WHERE id = ?",
                               [(k + 1, pid) for k, pid in enumerate(ordered)])
        return self.list()

    def export(self) -> dict[str, Any]:
        return {"format": EXPORT_FORMAT, "version": EXPORT_VERSION,
                "poses": [{"name": p.name, "x": p.x, "y": p.y, "theta": p.theta} for p in self.list()]}

    def import_poses(self, poses: builtins.list[tuple[str, float, float, float]], *,
                     replace: bool) -> builtins.list[PoseRecord]:
        """Append ``poses`` (name, x, y, theta) in order, after deleting all poses when ``replace``.

        All or nothing: one bad pose rejects the whole import (its index is named).
        """
        checked: builtins.list[tuple[str, float, float, float]] = []
        for i, pose in enumerate(poses):
            try:
                checked.append(check_pose(*pose))
            except PoseDbError as exc:
                raise PoseDbError(f"pose {i}: {exc}") from None
        now = time.time()
        with self._tx() as db:
            if replace:
                db.execute("DELETE FROM poses")
            self._check_room(db, len(checked))
            start = db.execute("SELECT COALESCE(MAX(position), 0) + 1 FROM poses").fetchone()[0]
            db.executemany(
                "INSERT INTO poses (name, x_m, y_m, theta_rad, position, created_at, updated_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                [(*p, start + k, now, now) for k, p in enumerate(checked)])
        return self.list()
