"""The pose database file made read-only under a running HMI: reads still work, writes get a clear error, no crash."""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.hmi_api.posedb import DB_FILE
from tests.support.hmi import HmiClient, base_url, hmi_stack, password_of, wait_http

pytestmark = pytest.mark.integration


@contextlib.contextmanager
def read_only(path: Path) -> Iterator[None]:
    """Make ``path`` unwritable, also for root (which ignores file modes: ``chattr +i`` there); restore after."""
    mode = path.stat().st_mode
    immutable = os.geteuid() == 0
    if immutable:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)]).returncode != 0:
            pytest.skip("running as root and the file system does not support chattr +i: cannot make it read-only")
    else:
        path.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
    try:
        with pytest.raises(PermissionError):
            path.open("ab").close()
        yield
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(path)], check=True)
        path.chmod(mode)


def test_read_only_pose_database_clear_error_no_crash(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    stack = hmi_stack(run_dir)
    try:
        stack.start()
        wait_http(stack)
        password = password_of(stack)
        with HmiClient(base_url(stack)) as c:
            c.login(password)
            assert c.post("/api/poses", json={"name": "dock", "x": 1.0, "y": 2.0, "theta": 0.0}).status_code in (
                200, 201)
        # a clean stop writes everything into the database file (no WAL left behind)
        stack.stop()
        db = run_dir / DB_FILE
        assert db.is_file()
        with read_only(db):
            again = hmi_stack(run_dir)
            stack = again
            again.start()
            wait_http(again)
            pid = again.pid("hmi_api")
            with HmiClient(base_url(again)) as c:
                c.login(password)  # the stored hash outlives the restart
                listed = c.get("/api/poses")
                assert listed.status_code == 200 and [p["name"] for p in listed.json()] == ["dock"]
                r = c.post("/api/poses", json={"name": "bay", "x": 3.0, "y": 1.0, "theta": 0.5})
                assert r.status_code == 503, r.text
                assert "read-only" in r.text or "readonly" in r.text, r.text
                assert c.get("/api/poses").status_code == 200
            assert again.pid("hmi_api") == pid, "hmi_api restarted after the refused write"
    finally:
        stack.stop()
