"""The HMI's answers to an outside probe (each test reproduces one request of that probe against the real service,
``zagv up --only hmi_api``): strict body decoding, ``?token=`` only where a header cannot be sent, WebSockets
closed on logout, anchored names, maps by name only, bounded query parameters, security headers, a Host allow-list,
API docs behind login, a pose cap, per-client login throttling, and HTTPS with the Zenoh LAN certificate tooling.
"""

from __future__ import annotations

import concurrent.futures
import shutil
import ssl
import subprocess
import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect as ws_connect

from services.hmi_api.app import SECURITY_HEADERS
from tests.support.hmi import HmiClient, base_url, hmi_stack, password_of, wait_http
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

FREE_ATTEMPTS = 3
MAX_POSES = 5
BODY_ROUTES = ["/api/login", "/api/jog", "/api/goal", "/api/initial_pose", "/api/mapping/save", "/api/mapping/stop",
               "/api/poses", "/api/poses/import", "/api/poses/1/move"]


@pytest.fixture(scope="module")
def hmi(tmp_path_factory):
    stack = hmi_stack(tmp_path_factory.mktemp("hmi_security"), sets=[
        "hmi_api.query_timeout_s=0.3", f"hmi_api.login_free_attempts={FREE_ATTEMPTS}",
        "hmi_api.login_lockout_initial_s=5.0", f"hmi_api.max_poses={MAX_POSES}"])
    try:
        stack.start()
        wait_http(stack)
        with HmiClient(base_url(stack)) as client:
            client.login(password_of(stack))
            yield stack, client
    finally:
        stack.stop()


def test_invalid_utf8_and_odd_content_types_get_4xx_never_500(hmi) -> None:
    stack, client = hmi
    anon = HmiClient(base_url(stack))
    r = anon.post("/api/login", content=b'{"password":"\xff"}', headers={"content-type": "application/json"})
    assert r.status_code == 400 and "not UTF-8" in r.json()["detail"], r.text
    for path in BODY_ROUTES:
        r = client.post(path, content=b'{"name":"\xc3\x28"}', headers={"content-type": "application/json"})
        assert r.status_code == 400, (path, r.status_code, r.text)
        for media in ("application/x-www-form-urlencoded", "text/plain", "multipart/form-data; boundary=x", ""):
            r = client.post(path, content=b"a=b", headers={"content-type": media})
            assert r.status_code == 415, (path, media, r.status_code, r.text)
    assert "UnicodeDecodeError" not in stack.output() and "Traceback" not in stack.output()


def test_query_token_only_on_the_websocket_and_downloads(hmi) -> None:
    stack, client = hmi
    anon = HmiClient(base_url(stack))
    r = anon.post(f"/api/drive/disable?token={client.token}", data={"a": "b"})  # a cross-site form post
    assert r.status_code == 401
    assert anon.get(f"/api/status?token={client.token}").status_code == 401
    assert anon.get(f"/api/velocities.csv?token={client.token}").status_code == 200
    assert anon.get(f"/api/poses/export?token={client.token}").status_code == 200


def test_websocket_closes_on_logout(hmi) -> None:
    stack, _ = hmi
    with HmiClient(base_url(stack)) as own:
        own.login(password_of(stack))
        with ws_connect(f"ws://127.0.0.1:{stack.http_port}/api/ws?token={own.token}") as ws:
            ws.recv(timeout=10)
            assert own.post("/api/logout").status_code == 200
            logged_out = time.monotonic()
            frames = 0
            with pytest.raises(ConnectionClosed) as closed:
                while time.monotonic() - logged_out < 10:
                    ws.recv(timeout=10)
                    frames += 1
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
            print(f"\nwebsocket closed {time.monotonic() - logged_out:.2f} s after logout, {frames} frame(s) later")
            assert frames <= 2  # at most the frames already on their way
        with pytest.raises(InvalidStatus):
            ws_connect(f"ws://127.0.0.1:{stack.http_port}/api/ws?token={own.token}").close()


@pytest.mark.parametrize("body", [{"name": "m1\n"}, {"name": "../m1"}, {"name": ".hidden"}])
def test_map_save_names_are_anchored(hmi, body) -> None:
    _, client = hmi
    assert client.post("/api/mapping/save", json=body).status_code == 422


@pytest.mark.parametrize("name", ["/dev/zero", "../world", "../../Makefile", "m1\n", "maps/m1"])
def test_mapping_stop_takes_a_name_never_a_path(hmi, name) -> None:
    _, client = hmi
    r = client.post("/api/mapping/stop", json={"map": name})
    assert r.status_code == 422 and "$.map" in r.json()["detail"], r.text
    assert client.post("/api/mapping/stop", json={"map": "corridor_built"}).status_code == 503  # a name passes


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "-1", "0", "1e9", "abc"])
def test_velocity_window_is_bounded(hmi, value) -> None:
    _, client = hmi
    assert client.get(f"/api/velocities?window_s={value}").status_code in (400, 422)
    assert client.get("/api/velocities?window_s=5").status_code == 200


def test_security_headers_host_allow_list_and_docs_behind_login(hmi) -> None:
    stack, client = hmi
    anon = HmiClient(base_url(stack))
    for r in (anon.get("/"), anon.get("/static/app.js"), anon.get("/api/status"), client.get("/api/status"),
              client.get("/api/no-such-route"), anon.post("/api/login", json={"password": 1})):
        for name, value in SECURITY_HEADERS.items():
            assert r.headers.get(name) == value, (r.request.url, name)
    assert "frame-ancestors 'none'" in SECURITY_HEADERS["content-security-policy"]
    r = anon.get("/", headers={"host": "rebind.example:8080"})
    assert r.status_code == 400 and "Host" in r.json()["detail"]
    assert anon.get("/", headers={"host": f"localhost:{stack.http_port}"}).status_code == 200
    with pytest.raises(InvalidStatus):
        ws_connect(f"ws://127.0.0.1:{stack.http_port}/api/ws?token={client.token}",
                   additional_headers={"Host": "rebind.example"}).close()
    assert anon.get("/api/schema/openapi.json").status_code == 401
    assert client.get("/api/schema/openapi.json").json()["openapi"].startswith("3.")
    for page in ("/api/schema/swagger", "/api/schema/redoc", "/api/schema/elements", "/api/schema/rapidoc"):
        assert client.get(page).status_code == 404, page  # no pages that pull scripts from a CDN


def test_pose_list_is_capped(hmi) -> None:
    _, client = hmi
    held = len(client.get("/api/poses").json())
    for i in range(MAX_POSES - held):
        assert client.post("/api/poses", json={"name": f"p{i}", "x": 1.0, "y": 2.0, "theta": 0.0}).status_code == 201
    r = client.post("/api/poses", json={"name": "one too many", "x": 1.0, "y": 2.0, "theta": 0.0})
    assert r.status_code == 409 and "limit of 5" in r.json()["detail"]
    r = client.post("/api/poses/import", json={"poses": [{"name": "a", "x": 0.0, "y": 0.0}]})
    assert r.status_code == 409
    assert len(client.get("/api/poses").json()) == MAX_POSES
    assert client.post("/api/poses", json={"name": "a\nb", "x": 1.0, "y": 2.0}).status_code in (409, 422)


def test_login_is_throttled_per_client_and_failures_are_logged(hmi) -> None:
    """Last in the module: it locks 127.0.0.1 out for a while."""
    stack, client = hmi
    anon = HmiClient(base_url(stack))
    mark = stack.line_count()
    codes = [anon.post("/api/login", json={"password": f"guess {i}"}).status_code for i in range(50)]
    # locked out after the third: a later 401 only when a lock-out (5 s, then doubling) ran out on a slow machine
    assert codes[:FREE_ATTEMPTS + 1] == [401] * FREE_ATTEMPTS + [429], codes
    assert codes.count(401) <= FREE_ATTEMPTS + 2, codes
    r = anon.post("/api/login", json={"password": password_of(stack)})  # the right one, while locked out
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    retry_after_s = int(r.headers["retry-after"])
    stack.wait_line(r"^\S+\s+\| .*login failed from 127\.0\.0\.1 \(3 wrong password", timeout_s=5, after=mark)
    # 20 parallel wrong logins from a locked client: refused before any password hashing; the API stays responsive
    with concurrent.futures.ThreadPoolExecutor(20) as pool:
        parallel = list(pool.map(lambda i: anon.post("/api/login", json={"password": f"p{i}"}).status_code,
                                 range(20)))
        started = time.monotonic()
        assert client.get("/api/robot").status_code == 200
        robot_s = time.monotonic() - started
    assert set(parallel) == {429}, parallel
    print(f"\nlogin: {codes.count(401)} x 401 then {codes.count(429)} x 429; /api/robot in {robot_s * 1e3:.0f} ms "
          "after 20 parallel guesses")
    hashed = sum("login failed from" in line for line in stack.output().splitlines()[mark:])
    assert hashed == codes.count(401), f"{hashed} passwords hashed, {codes.count(401)} answered 401"
    # the lock-out ends by itself: the right password works again
    wait_for_sync(lambda: anon.post("/api/login", json={"password": password_of(stack)}).status_code == 200,
                  timeout_s=retry_after_s + 30, poll_s=1.0, message="the lock-out never ended")


def test_hmi_serves_https_with_the_lan_certificate_tooling(tmp_path) -> None:
    if not shutil.which("openssl") or not shutil.which("sh"):
        pytest.skip("openssl (and sh) are needed to make the test certificates; not found on PATH")
    from services.launch.stack_process import REPO_ROOT

    pki = tmp_path / "pki"
    for args in (["ca"], ["zagv-hmi-web", "DNS:localhost", "IP:127.0.0.1"]):
        subprocess.run(["sh", str(REPO_ROOT / "deploy" / "zenoh" / "make-certs.sh"), str(pki), *args], check=True,
                       capture_output=True, timeout=60)
    stack = hmi_stack(tmp_path / "run", sets=[f'hmi_api.tls_certificate="{pki / "zagv-hmi-web.pem"}"',
                                             f'hmi_api.tls_private_key="{pki / "zagv-hmi-web.key"}"'])
    (tmp_path / "run").mkdir()
    try:
        stack.start()
        url = f"https://127.0.0.1:{stack.http_port}"
        context = ssl.create_default_context(cafile=str(pki / "ca.pem"))

        def answers() -> bool:
            try:
                return httpx.get(url + "/", verify=context, timeout=2.0).status_code == 200
            except httpx.TransportError:
                return False

        wait_for_sync(answers, timeout_s=30, poll_s=0.2, message="no HTTPS answer")
        r = httpx.post(url + "/api/login", json={"password": password_of(stack)}, verify=context, timeout=10)
        assert r.status_code == 200
        with pytest.raises(httpx.TransportError):  # plain HTTP is not served on the TLS port
            httpx.get(f"http://127.0.0.1:{stack.http_port}/", timeout=5.0)
        stack.wait_line(r"HMI at https://", timeout_s=5)
    finally:
        stack.stop()
