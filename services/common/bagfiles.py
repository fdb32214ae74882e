"""Saved black box bags (rosbag2 folders ``blackbox_*``) in a folder: size, duration and message count from their
``metadata.yaml``. Shared by the recorder's CLI and the HMI, which list what the recorder service wrote."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml


@dataclass(frozen=True)
class SavedBag:
    name: str
    size_bytes: int
    duration_s: float
    messages: int
    modified_s: float


def list_bags(folder: Path) -> list[SavedBag]:
    """Every ``blackbox_*`` rosbag2 folder in ``folder`` (newest first); unreadable metadata counts as empty."""
    out: list[SavedBag] = []
    if not folder.is_dir():
        return out
    for bag in folder.glob("blackbox_*"):
        meta = bag / "metadata.yaml"
        if not meta.is_file():
            continue  # still being written
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            duration = info["duration"]["nanoseconds"] / 1e9
            count = int(info["message_count"])
        except (OSError, KeyError, TypeError, yaml.YAMLError):
            duration, count = 0.0, 0
        size = sum(f.stat().st_size for f in bag.iterdir() if f.is_file())
        out.append(SavedBag(bag.name, size, duration, count, meta.stat().st_mtime))
    return sorted(out, key=lambda b: b.modified_s, reverse=True)
