"""Inspection tools print JSON for a test message: ``zagv topic echo`` and the zenoh-cli ``zagv`` decoder."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from proto import Keys, encode
from proto.messages import Twist2D
from services.common.session import open_session, router_settings
from services.common.settings import ZenohSettings
from tests.support.waiting import wait_for_sync

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def publishing_router(free_port):
    """A router with a client publishing a Twist2D on agv/r1/cmd_vel every 20 ms."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    router = open_session(router_settings([endpoint]))
    client = open_session(ZenohSettings(connect=[endpoint]))
    stop = threading.Event()

    def publish() -> None:
        pub = client.declare_publisher(Keys("r1")("cmd_vel"))
        while not stop.wait(0.02):
            pub.put(encode(Twist2D(vx=0.125, vy=-0.05, wz=0.25, stamp=1.5)))

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    yield endpoint
    stop.set()
    t.join()
    client.close()
    router.close()


def _first_json_line(argv: list[str], timeout_s: float = 30.0) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO_ROOT)
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout
        for line in proc.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    try:
        wait_for_sync(lambda: lines, timeout_s=timeout_s, message=f"no output from {argv[:4]}")
    finally:
        proc.kill()
        _, err = proc.communicate()
    assert lines, err
    return json.loads(lines[0])


def test_topic_echo_prints_json(publishing_router):
    msg = _first_json_line([sys.executable, "-m", "services.cli", "topic", "echo", "cmd_vel", "--json",
                            "--count", "1", "--connect", publishing_router])
    assert msg == {"vx": 0.125, "vy": -0.05, "wz": 0.25, "stamp": 1.5}


def test_zenoh_cli_decoder_plugin_prints_json(publishing_router):
    zenoh_cli = shutil.which("zenoh", path=str(Path(sys.executable).parent))
    if zenoh_cli is None:
        pytest.skip("zenoh-cli is not installed in this environment (pip install zenoh-cli)")
    msg = _first_json_line([zenoh_cli, "--mode", "client", "--connect", publishing_router,
                            "--cfg", "scouting/multicast/enabled:false", "subscribe", "-k", "agv/**",
                            "--decoder", "zagv"])
    assert msg["vx"] == 0.125 and msg["wz"] == 0.25
