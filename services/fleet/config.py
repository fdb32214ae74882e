"""The ``[fleet]`` table: where the site's fleet view listens, its login, and how it shows the robots."""

from __future__ import annotations

import msgspec

from services.common.web_config import check_web_access, host_allow_list


class FleetConfig(msgspec.Struct, forbid_unknown_fields=True):
    """fleet settings (defaults for a site server on loopback).

    Login works as in the robot's HMI (``services.common.auth``): ``password_hash`` from ``python -m
    services.common.auth hash``, else a first-run password stored in ``state_dir`` and printed once; ``login_*``,
    ``allowed_hosts`` and ``tls_*`` as in ``[hmi_api]``. ``robots`` lists the robot ids shown (empty: every robot
    whose health tokens reach the site); ``map_from`` names the robot whose ``map`` is the site map (empty: the
    first robot, by id, that published one). Battery charge is linear in the drive's battery voltage between
    ``battery_empty_v`` and ``battery_full_v``.
    """

    host: str = "127.0.0.1"
    port: int = 8090
    state_dir: str = "var/fleet"
    password_hash: str = ""
    token_ttl_s: float = 12 * 3600.0
    login_free_attempts: int = 5
    login_lockout_initial_s: float = 1.0
    login_lockout_max_s: float = 300.0
    #: Host header values accepted (DNS rebinding): empty = loopback names plus ``host`` when it is not a wildcard
    allowed_hosts: list[str] = msgspec.field(default_factory=list)
    tls_certificate: str = ""
    tls_private_key: str = ""
    #: WebSocket frames per second (wall time: a person watches them)
    ws_rate_hz: float = 10.0
    #: how long a goal, pose list, cancel or e-stop waits for the robot's answer (s)
    query_timeout_s: float = 3.0
    robots: list[str] = msgspec.field(default_factory=list)
    map_from: str = ""
    #: the most points of a robot's path sent to the browser (the path is decimated beyond)
    path_max_points: int = 400
    #: the most poses of one pose list
    max_poses: int = 200
    battery_empty_v: float = 44.0
    battery_full_v: float = 52.0

    def __post_init__(self) -> None:
        check_web_access("fleet", password_hash=self.password_hash, port=self.port,
                         tls_certificate=self.tls_certificate, tls_private_key=self.tls_private_key,
                         positive={name: getattr(self, name) for name in (
                             "ws_rate_hz", "token_ttl_s", "query_timeout_s", "login_lockout_initial_s",
                             "login_lockout_max_s")})
        if self.login_free_attempts < 1 or self.max_poses < 1 or self.path_max_points < 2:
            raise ValueError("fleet.login_free_attempts and fleet.max_poses must be >= 1, path_max_points >= 2")
        if not self.battery_full_v > self.battery_empty_v:
            raise ValueError("fleet.battery_full_v must be above fleet.battery_empty_v")

    def host_allow_list(self) -> list[str]:
        """The Host header names accepted (``web_config.host_allow_list``)."""
        return host_allow_list(self.host, self.allowed_hosts)
