"""``localization/mode`` chooses a map by name from the maps folder, never by path, and reads map files with size
and type limits (reproductions of an outside probe: ``{"map": "/dev/zero"}`` hung localization and grew it without
bound; ``"../world"`` loaded a YAML outside the maps folder and the error quoted the file's first line)."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import pytest

from proto.messages import ModeRequest, SaveMapRequest
from services.common.map_io import MAX_YAML_BYTES, MapError, load_map, read_map_yaml
from services.common.node import QueryError, query
from services.launch.stack_process import REPO_ROOT, Stack

pytestmark = pytest.mark.integration

MAKEFILE_FIRST_LINE = (REPO_ROOT / "Makefile").read_text().splitlines()[0]


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


@pytest.fixture(scope="module")
def mapping_stack(tmp_path_factory: pytest.TempPathFactory):
    run_dir = tmp_path_factory.mktemp("map_names")
    stack = Stack(run_dir, ["localization"], sim=False, extra_args=["--mapping"])
    try:
        stack.start()
        yield stack
    finally:
        stack.stop()


def _query(stack: Stack, name: str, request, timeout_s: float = 5.0):
    """One query, retried while no queryable answers yet (the health token may precede the queryables)."""
    session = stack.session()
    deadline = time.monotonic() + 30.0
    while True:
        try:
            return asyncio.run(query(session, stack.keys, name, request, timeout_s=timeout_s))
        except QueryError as exc:
            if "no queryable answered" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def _mode(stack: Stack, map_name: str):
    return _query(stack, "localization/mode", ModeRequest(mode="navigation", map_yaml=map_name))


@pytest.mark.parametrize("name", ["/dev/zero", "../world", "../../Makefile", str(REPO_ROOT / "Makefile"),
                                  "maps/../x", "m1\n", ".hidden", "-x", "a/b", "x" * 65])
def test_a_path_is_refused_at_once_naming_the_rule(mapping_stack: Stack, name: str) -> None:
    pid = mapping_stack.pid("localization")
    rss_before = _rss_mb(pid)
    started = time.monotonic()
    reply = _mode(mapping_stack, name)
    took_s = time.monotonic() - started
    assert not reply.ok
    assert "not a map name" in reply.message and "chosen by name" in reply.message, reply.message
    assert MAKEFILE_FIRST_LINE not in reply.message
    assert took_s < 5.0
    assert mapping_stack.pid("localization") == pid and _rss_mb(pid) - rss_before < 20


def test_files_in_the_maps_folder_are_type_and_size_checked(mapping_stack: Stack) -> None:
    maps = mapping_stack.run_dir / "maps"
    maps.mkdir(exist_ok=True)
    (maps / "zero.yaml").symlink_to("/dev/zero")
    (maps / "project.yaml").write_bytes((REPO_ROOT / "Makefile").read_bytes())
    (maps / "huge.yaml").write_bytes(b"#" * (MAX_YAML_BYTES + 1))
    os.mkfifo(maps / "fifo.yaml")
    pid = mapping_stack.pid("localization")
    for name, reason in (("zero", "not a regular file"), ("project", "not a map YAML"),
                         ("huge.yaml", "more than"), ("fifo", "not a regular file"), ("absent", "no map named")):
        reply = _mode(mapping_stack, name)
        assert not reply.ok and reason in reply.message, (name, reply.message)
        assert MAKEFILE_FIRST_LINE not in reply.message and ".PHONY" not in reply.message
    # still answering and still the same process
    assert mapping_stack.pid("localization") == pid
    reply = _query(mapping_stack, "localization/save_map", SaveMapRequest(name="m1\n"))
    assert not reply.ok and "map name" in reply.message
    assert not (maps / "m1\n.yaml").exists()


def test_map_io_limits_without_a_service(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="not a regular file"):
        read_map_yaml("/dev/zero")
    with pytest.raises(MapError, match="not a regular file"):
        read_map_yaml(tmp_path)
    (tmp_path / "m.yaml").write_text("image: /dev/zero\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapError, match="not a regular file"):
        load_map(tmp_path / "m.yaml")
    (tmp_path / "s.yaml").write_text("image: [secret words]\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapError) as err:
        read_map_yaml(tmp_path / "s.yaml")
    assert "secret" not in str(err.value) and "a list" in str(err.value)
