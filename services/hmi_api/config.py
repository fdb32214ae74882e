"""The ``[hmi_api]`` table: where the API listens, where its state lives, login and the robot's home pose."""

from __future__ import annotations

import msgspec


class HmiApiConfig(msgspec.Struct, forbid_unknown_fields=True):
    """hmi_api settings (defaults for the simulated robot).

    ``password_hash`` is a ``scrypt$...`` string from ``python -m services.hmi_api.auth hash``; when empty, a
    first-run password is generated, its hash stored in ``state_dir`` and the password printed once.
    ``home_*`` is the start pose that ``POST /api/home`` sends as a goal (the paper's "return to zero").
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

    def __post_init__(self) -> None:
        if self.password_hash:
            from services.hmi_api.auth import check_hash_format

            check_hash_format(self.password_hash)
        if not 0 < self.port < 65536:
            raise ValueError(f"hmi_api.port must be in 1..65535, got {self.port}")
        for name in ("jog_timeout_s", "jog_rate_hz", "ws_rate_hz", "velocity_record_hz", "token_ttl_s",
                     "velocity_history_s", "query_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"hmi_api.{name} must be > 0, got {getattr(self, name)}")
