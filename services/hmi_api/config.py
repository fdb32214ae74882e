"""The ``[hmi_api]`` table: where the API listens, where its state lives, login and the robot's home pose."""

from __future__ import annotations

import msgspec

from services.common.web_config import check_web_access, host_allow_list


class HmiApiConfig(msgspec.Struct, forbid_unknown_fields=True):
    """hmi_api settings (defaults for the simulated robot).

    ``password_hash`` is a ``scrypt$...`` string from ``python -m services.hmi_api.auth hash``; when empty, a
    first-run password is generated, its hash stored in ``state_dir`` and the password printed once.
    ``allowed_hosts``, ``tls_*``, ``login_*`` and ``max_poses`` are the limits deploy/README.md ("Threat model")
    describes. ``home_*`` is the start pose that ``POST /api/home`` sends as a goal (the paper's "return to zero").
    """

    host: str = "127.0.0.1"
    port: int = 8080
    state_dir: str = "var/hmi"
    password_hash: str = ""
    token_ttl_s: float = 12 * 3600.0
    jog_timeout_s: float = 0.3
    jog_rate_hz: float = 20.0
    ws_rate_hz: float = 15.0
    velocity_record_hz: float = 10.0
    velocity_history_s: float = 600.0
    home_x_m: float = 0.0
    home_y_m: float = 0.0
    home_theta_rad: float = 0.0
    scan_max_points: int = 720
    particles_max: int = 1000
    query_timeout_s: float = 3.0
    #: how long ``POST /api/blackbox/save`` waits for the recorder to have written the bag
    blackbox_save_timeout_s: float = 30.0
    #: wrong passwords a client may send before it is locked out (1 s, doubling up to login_lockout_max_s)
    login_free_attempts: int = 5
    login_lockout_initial_s: float = 1.0
    login_lockout_max_s: float = 300.0
    #: the most poses the pose database holds
    max_poses: int = 1000
    #: Host header values accepted (DNS rebinding): empty = loopback names plus ``host`` when it is not a wildcard
    allowed_hosts: list[str] = msgspec.field(default_factory=list)
    #: HTTPS: PEM certificate and private key (e.g. from deploy/zenoh/make-certs.sh); both empty = plain HTTP
    tls_certificate: str = ""
    tls_private_key: str = ""

    def __post_init__(self) -> None:
        check_web_access("hmi_api", password_hash=self.password_hash, port=self.port,
                         tls_certificate=self.tls_certificate, tls_private_key=self.tls_private_key,
                         positive={name: getattr(self, name) for name in (
                             "jog_timeout_s", "jog_rate_hz", "ws_rate_hz", "velocity_record_hz", "token_ttl_s",
                             "velocity_history_s", "query_timeout_s", "blackbox_save_timeout_s",
                             "login_lockout_initial_s", "login_lockout_max_s")})
        if self.login_free_attempts < 1 or self.max_poses < 1:
            raise ValueError("hmi_api.login_free_attempts and hmi_api.max_poses must be >= 1")

    def host_allow_list(self) -> list[str]:
        """The Host header names accepted (``web_config.host_allow_list``)."""
        return host_allow_list(self.host, self.allowed_hosts)
