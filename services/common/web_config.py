"""Checks and defaults shared by the configs of zagv's web front ends (``[hmi_api]``, ``[fleet]``); no web imports,
so a config loads without the web stack."""

from __future__ import annotations

from services.common.auth import check_hash_format

#: Host header names a server bound to loopback answers to
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1", "[::1]")


def check_web_access(table: str, *, password_hash: str, port: int, tls_certificate: str, tls_private_key: str,
                     positive: dict[str, float]) -> None:
    """ValueError naming ``table.key`` for: a malformed password hash, a port outside 1..65535, half a TLS pair, or
    a value of ``positive`` (name -> value) that is not > 0."""
    if password_hash:
        check_hash_format(password_hash, f"{table}.password_hash")
    if not 0 < port < 65536:
        raise ValueError(f"{table}.port must be in 1..65535, got {port}")
    if bool(tls_certificate) != bool(tls_private_key):
        raise ValueError(f"{table}.tls_certificate and {table}.tls_private_key go together: set both or neither")
    for name, value in positive.items():
        if not value > 0:
            raise ValueError(f"{table}.{name} must be > 0, got {value}")


def host_allow_list(host: str, allowed_hosts: list[str]) -> list[str]:
    """The Host header names accepted (DNS rebinding): ``allowed_hosts``, else the loopback names plus ``host``
    unless it is a wildcard."""
    if allowed_hosts:
        return list(allowed_hosts)
    names = list(LOOPBACK_NAMES)
    if host not in ("0.0.0.0", "::", "") and host not in names:
        names.append(host)
    return names
