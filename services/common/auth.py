"""Login of the web HMIs (the robot's hmi_api, the site's fleet view): scrypt password hashes, the first-run
password, bearer tokens and per-client login throttling.

Hash format: ``scrypt$<n>$<r>$<p>$<salt b64>$<key b64>`` (hashlib.scrypt, 16-byte random salt, 32-byte key).
Run ``python -m services.common.auth hash`` (or ``python -m services.hmi_api.auth hash``) to make a hash for
``hmi_api.password_hash`` or ``fleet.password_hash``.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import getpass
import hashlib
import hmac
import logging
import math
import os
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path

SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
FIRST_RUN_FILE = "hmi_password.scrypt"
#: letters and digits a person reads without confusion (no 0/O, 1/l/I)
_READABLE = "abcdefghijkmnpqrstuvwxyz23456789"


def hash_password(password: str, *, n: int = SCRYPT_N, r: int = SCRYPT_R, p: int = SCRYPT_P) -> str:
    """A salted scrypt hash of ``password`` in the ``scrypt$n$r$p$salt$key`` format."""
    salt = os.urandom(16)
    key = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=32)
    b64 = base64.b64encode
    return f"scrypt${n}${r}${p}${b64(salt).decode()}${b64(key).decode()}"


def check_hash_format(stored: str, key: str = "password_hash") -> None:
    """Raise ValueError naming the problem (and the config ``key``) when ``stored`` is not a usable scrypt hash."""
    parts = stored.split("$")
    if len(parts) != 6 or parts[0] != "scrypt":
        raise ValueError(f"{key} must look like scrypt$n$r$p$salt$key "
                         "(make one with: python -m services.common.auth hash)")
    try:
        n, r, p = (int(v) for v in parts[1:4])
        base64.b64decode(parts[4], validate=True)
        base64.b64decode(parts[5], validate=True)
    except ValueError as exc:
        raise ValueError(f"{key} is malformed: {exc}") from None
    if n < 2 or n & (n - 1) or r < 1 or p < 1:
        raise ValueError(f"{key} has bad scrypt parameters (n a power of two > 1, r, p >= 1)")


def verify_password(password: str, stored: str) -> bool:
    """True when ``password`` matches the ``stored`` hash (constant-time comparison)."""
    check_hash_format(stored)
    _, n, r, p, salt, key = stored.split("$")
    expected = base64.b64decode(key)
    got = hashlib.scrypt(password.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p),
                         dklen=len(expected))
    return hmac.compare_digest(got, expected)


def new_password(groups: int = 3, size: int = 4) -> str:
    """A random password such as ``k7qm-x2rf-9wna`` (about 60 bits)."""
    return "-".join("".join(secrets.choice(_READABLE) for _ in range(size)) for _ in range(groups))


def first_run_hash(state_dir: Path) -> tuple[str, str | None]:
    """The stored first-run hash in ``state_dir``, creating one on first use.

    Returns (hash, password) where password is the new plain password when it was just created (to be shown
    once), else None. The file is written atomically with mode 0600.
    """
    path = state_dir / FIRST_RUN_FILE
    if path.exists():
        stored = path.read_text().strip()
        check_hash_format(stored)
        return stored, None
    state_dir.mkdir(parents=True, exist_ok=True)
    password = new_password()
    stored = hash_password(password)
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(stored + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return stored, password


@dataclass
class TokenStore:
    """Bearer tokens with an expiry. Times are wall-clock monotonic seconds: token lifetime is about the
    operator's session, not robot timing, so it does not follow the simulated clock."""

    ttl_s: float
    _tokens: dict[str, float] = field(default_factory=dict)

    def issue(self) -> str:
        self._prune()
        token = secrets.token_urlsafe(32)
        self._tokens[token] = time.monotonic() + self.ttl_s
        return token

    def valid(self, token: str | None) -> bool:
        if not token:
            return False
        expiry = self._tokens.get(token)
        if expiry is None:
            return False
        if expiry < time.monotonic():
            self._tokens.pop(token, None)
            return False
        return True

    def revoke(self, token: str) -> None:
        self._tokens.pop(token, None)

    def _prune(self) -> None:
        now = time.monotonic()
        for t in [t for t, e in self._tokens.items() if e < now]:
            del self._tokens[t]


@dataclass
class _Failures:
    count: int = 0
    locked_until: float = 0.0
    last_at: float = 0.0


@dataclass
class LoginThrottle:
    """Per-client login throttling (core: times are arguments).

    After ``free_attempts`` wrong passwords in a row a client (its address) is locked out for ``lockout_initial_s``,
    doubling with each further wrong one up to ``lockout_max_s``. A lock-out is checked before the password is
    hashed, so a locked client costs no scrypt time; one attempt per client is hashed at a time. A client unheard of for
    ``forget_after_s`` starts afresh; at most ``max_clients`` are remembered (the oldest forgotten first).
    A correct password clears the client's record.
    """

    free_attempts: int = 5
    lockout_initial_s: float = 1.0
    lockout_max_s: float = 300.0
    forget_after_s: float = 900.0
    max_clients: int = 10000
    _clients: dict[str, _Failures] = field(default_factory=dict)
    _busy: set[str] = field(default_factory=set)

    def wait_s(self, client: str, now: float) -> float:
        """Seconds until ``client`` may try again (0: now), or ``inf`` while one of its attempts is being checked."""
        if client in self._busy:
            return math.inf
        record = self._clients.get(client)
        if record is None:
            return 0.0
        if now - record.last_at > self.forget_after_s:
            del self._clients[client]
            return 0.0
        return max(0.0, record.locked_until - now)

    def begin(self, client: str) -> None:
        self._busy.add(client)

    def end(self, client: str, ok: bool, now: float) -> int:
        """Record the outcome of ``client``'s attempt; returns its count of consecutive failures."""
        self._busy.discard(client)
        if ok:
            self._clients.pop(client, None)
            return 0
        record = self._clients.pop(client, None) or _Failures()
        self._clients[client] = record  # re-inserted: the dict keeps clients in order of last attempt
        record.count += 1
        record.last_at = now
        over = record.count - self.free_attempts
        if over >= 0:
            record.locked_until = now + min(self.lockout_max_s, self.lockout_initial_s * 2.0 ** over)
        while len(self._clients) > self.max_clients:
            del self._clients[next(iter(self._clients))]
        return record.count


class LoginThrottled(RuntimeError):
    """A client locked out after wrong passwords, or with an attempt still being checked: retry after
    ``retry_after_s``."""

    def __init__(self, retry_after_s: float, message: str) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class PasswordLogin:
    """Password login of one web service: per-client throttling, one scrypt at a time (guessing cannot take every
    CPU), a bearer token for the right password."""

    def __init__(self, password_hash: str, *, token_ttl_s: float, free_attempts: int, lockout_initial_s: float,
                 lockout_max_s: float, log: logging.Logger) -> None:
        self.password_hash = password_hash
        self.tokens = TokenStore(ttl_s=token_ttl_s)
        self.throttle = LoginThrottle(free_attempts=free_attempts, lockout_initial_s=lockout_initial_s,
                                      lockout_max_s=lockout_max_s)
        self._hashing = asyncio.Semaphore(1)
        self._log = log

    async def login(self, password: str, client: str) -> str | None:
        """A token for the right password, None for a wrong one (logged with the client's address); raises
        LoginThrottled while ``client`` is locked out or has an attempt being checked."""
        wait_s = self.throttle.wait_s(client, time.monotonic())
        if wait_s > 0:
            if math.isinf(wait_s):
                raise LoginThrottled(1.0, "a login from this client is being checked; try again in a moment")
            raise LoginThrottled(wait_s, f"too many wrong passwords from this client; try again in {wait_s:.0f} s")
        self.throttle.begin(client)
        ok = False
        try:
            async with self._hashing:
                loop = asyncio.get_running_loop()
                ok = await loop.run_in_executor(None, verify_password, password, self.password_hash)
        finally:
            failures = self.throttle.end(client, ok, time.monotonic())
        if not ok:
            self._log.warning("login failed from %s (%d wrong password(s) in a row)", client, failures)
            return None
        self._log.info("login from %s", client)
        return self.tokens.issue()


def main(argv: list[str] | None = None, prog: str = "python -m services.common.auth") -> int:
    p = argparse.ArgumentParser(prog=prog, description="HMI password hashes")
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("hash", help="read a password and print its hash for hmi_api.password_hash or fleet.password_hash")
    args = p.parse_args(argv)
    if args.cmd == "hash":
        password = getpass.getpass("password: ")
        if len(password) < 8:
            print("a password needs at least 8 characters")
            return 2
        print(hash_password(password))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
