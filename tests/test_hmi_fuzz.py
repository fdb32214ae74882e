"""API fuzz run: schemathesis generates valid and invalid requests for every operation of the OpenAPI document
served by the running hmi_api; no response may be a server error, and no response may carry NaN.

After the generated cases, every operation also gets bodies that are not UTF-8 and bodies under odd content types
(form, text, multipart, XML, none): each must be a 4xx. The hmi_api process may not grow by more than 50 MB of
resident memory over the whole run.

With hmi_api alone, operations that need a robot service answer 503 "robot service unavailable: <query>" (a correct
answer, not a crash); that 503 is the only 5xx allowed there, and only with that text. Against the whole simulated
stack no 5xx at all is allowed.
"""

from __future__ import annotations

import collections
import json

import pytest
import schemathesis  # the dev extra
from hypothesis import HealthCheck, given, settings

from tests.support.hmi import (
    HmiClient,
    base_url,
    full_stack_available,
    hmi_stack,
    missing_services,
    password_of,
    wait_http,
)

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SKIP = {("POST", "/api/logout")}  # would end the fuzzer's own session
EXAMPLES = {"/api/login": 4}


def reject_constant(name: str) -> None:
    raise ValueError(f"{name} in JSON output")


def fuzz_operation(op, mode, url, token, statuses, problems, allow_unavailable):
    """A hypothesis test over one operation: call it, count the status, record any server error or NaN."""

    @settings(max_examples=EXAMPLES.get(op.path, 12), deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(case=op.as_strategy(generation_mode=mode))
    def run(case):
        response = case.call(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=10)
        statuses[(f"{op.method.upper()} {op.path}", response.status_code)] += 1
        text = response.content.decode("utf-8", "replace")  # /api/map.png is binary
        if "application/json" in str(response.headers.get("content-type")):
            try:
                json.loads(text, parse_constant=reject_constant)
            except ValueError as exc:
                problems.append(f"{op.method} {op.path}: not strict JSON ({exc}): {text[:200]}")
        unavailable = response.status_code == 503 and "robot service unavailable" in text
        if response.status_code >= 500 and not (allow_unavailable and unavailable):
            problems.append(f"{case.method} {case.formatted_path} body={case.body!r}: "
                            f"{response.status_code} {text[:300]}")

    return run


#: bodies and content types a client might send by mistake or on purpose
ODD_BODIES = [
    ("application/json", b'{"password":"\xff"}'), ("application/json", b'{"name":"\xc3\x28","x":1}'),
    ("application/json", b"\xfe\xff\x00{"), ("application/json; charset=latin-1", b'{"name":"caf\xe9"}'),
    ("application/x-www-form-urlencoded", b"name=a&x=1"), ("text/plain", b'{"name":"a"}'),
    ("multipart/form-data; boundary=zz", b"--zz\r\ncontent-disposition: form-data; name=a\r\n\r\n1\r\n--zz--"),
    ("application/xml", b"<a/>"), ("", b"\x00\x01\x02"), ("application/json", b"\xff" * 4096),
]
RSS_GROWTH_LIMIT_MB = 50.0


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


def fuzz_odd_bodies(url: str, token: str, operations: list, statuses, problems) -> None:
    """Send ``ODD_BODIES`` to every operation; anything but a 4xx (or a 503 naming a robot service) is a problem."""
    with HmiClient(url) as client:
        client.headers["authorization"] = f"Bearer {token}"
        for method, path in operations:
            concrete = path.replace("{pose_id}", "1")
            for media, body in ODD_BODIES:
                headers = {"content-type": media} if media else {}
                r = client.request(method, concrete, content=body, headers=headers)
                statuses[(f"{method} {path} (odd body)", r.status_code)] += 1
                if r.status_code >= 500 and "robot service unavailable" not in r.text:
                    problems.append(f"{method} {concrete} {media!r} {body[:20]!r}: {r.status_code} {r.text[:200]}")


def run_fuzz(stack, *, allow_unavailable: bool) -> None:
    """Fuzz every operation of the running stack's HMI; 503 "robot service unavailable" only if allowed."""
    wait_http(stack)
    url = base_url(stack)
    with HmiClient(url) as client:
        client.login(password_of(stack))
        client.post("/api/poses", json={"name": "seed", "x": 1.0, "y": 2.0, "theta": 0.0})
        token = client.token
    pid = stack.pid("hmi_api")
    rss_before = rss_mb(pid)
    schema = schemathesis.openapi.from_url(f"{url}/api/schema/openapi.json",
                                           headers={"Authorization": f"Bearer {token}"})
    statuses: collections.Counter[tuple[str, int]] = collections.Counter()
    problems: list[str] = []
    operations = 0
    routes: list[tuple[str, str]] = []
    for result in schema.get_all_operations():
        op = result.ok()
        if (op.method.upper(), op.path) in SKIP:
            continue
        operations += 1
        routes.append((op.method.upper(), op.path))
        for mode in (schemathesis.GenerationMode.POSITIVE, schemathesis.GenerationMode.NEGATIVE):
            try:
                fuzz_operation(op, mode, url, token, statuses, problems, allow_unavailable)()
            except schemathesis.errors.SerializationNotPossible:
                continue  # a negative mode that cannot be expressed as a request
    fuzz_odd_bodies(url, token, routes, statuses, problems)
    rss_growth = rss_mb(pid) - rss_before
    assert stack.pid("hmi_api") == pid, "hmi_api restarted during the fuzz run"
    total = sum(statuses.values())
    server_errors = sum(n for (_, code), n in statuses.items() if code >= 500)
    codes = dict(collections.Counter(code for (_, code) in statuses.elements()))
    print(f"\nfuzz: {total} requests over {operations} operations; 5xx: {server_errors}; codes: {codes}; "
          f"hmi_api RSS {rss_before:.1f} MB -> {rss_before + rss_growth:.1f} MB ({rss_growth:+.1f} MB)")
    assert operations >= 20 and total >= 200
    assert not problems, "\n".join(problems[:20])
    assert rss_growth <= RSS_GROWTH_LIMIT_MB, f"hmi_api grew by {rss_growth:.1f} MB during the fuzz run"


def test_fuzz_openapi_finds_no_server_error(tmp_path):
    stack = hmi_stack(tmp_path, sets=["hmi_api.query_timeout_s=0.1", "hmi_api.blackbox_save_timeout_s=0.1"])
    try:
        stack.start()
        run_fuzz(stack, allow_unavailable=True)
    finally:
        stack.stop()


@pytest.mark.skipif(not full_stack_available(),
                    reason=f"needs the simulated stack; missing services: {', '.join(missing_services())}")
def test_fuzz_against_the_simulated_robot_finds_no_server_error(tmp_path):
    stack = hmi_stack(tmp_path, full=True)
    try:
        stack.start(ready_timeout_s=120)
        run_fuzz(stack, allow_unavailable=False)
    finally:
        stack.stop()
