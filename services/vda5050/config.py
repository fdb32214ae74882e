"""The [vda5050] table: the MQTT broker, the VDA 5050 topic names and the vehicle's protocol behaviour."""

from __future__ import annotations

import msgspec


class Vda5050Config(msgspec.Struct, forbid_unknown_fields=True):
    """VDA 5050 2.0 vehicle interface ([vda5050]).

    Topics are ``{interface_name}/{major_version}/{manufacturer}/{serial_number}/{topic}`` (VDA 5050 §6.2);
    ``serial_number`` empty means the robot id. ``broker_host``/``broker_port`` name any MQTT 3.1.1/5 broker (the
    site's, or the one ``zagv up --vda5050`` embeds).
    """

    broker_host: str = "127.0.0.1"
    broker_port: int = 1883
    broker_username: str = ""
    broker_password: str = ""
    interface_name: str = "uagv"
    major_version: str = "v2"
    #: the protocol version written in every header ([Major].[Minor].[Patch])
    protocol_version: str = "2.0.0"
    manufacturer: str = "zagv"
    serial_number: str = ""
    #: the mapId of the map localization runs on; order nodes on another map are rejected
    map_id: str = "map"
    #: state is published on every change and at least this often (VDA 5050 §6.10: at most 30 s apart)
    state_interval_s: float = 30.0
    visualization_hz: float = 1.0
    #: used when a node's allowedDeviationXy / allowedDeviationTheta is 0 ("the manufacturer's normal tolerance")
    default_deviation_xy_m: float = 0.1
    default_deviation_theta_rad: float = 0.1
    #: below these the vehicle counts as standing still (state.driving false)
    driving_speed_mps: float = 0.01
    driving_turn_radps: float = 0.02
    #: battery charge is interpolated linearly from the RoboteQ battery voltage between these two
    battery_empty_v: float = 44.0
    battery_full_v: float = 52.0
    #: the most message errors (validation, rejections) kept in state; older ones drop out first
    max_message_errors: int = 20
    reconnect_delay_s: float = 1.0
    #: series data of the factsheet
    series_name: str = "zagv dual-swerve"
    max_load_mass_kg: float = 100.0
    height_max_m: float = 0.5

    def __post_init__(self) -> None:
        for name in ("interface_name", "major_version", "manufacturer", "serial_number"):
            value = getattr(self, name)
            if any(c in value for c in "/+#"):
                raise ValueError(f"vda5050.{name} {value!r} must not contain '/', '+' or '#' (it is a topic level)")
        if not 0 < self.state_interval_s <= 30.0:
            raise ValueError(f"vda5050.state_interval_s {self.state_interval_s} must be in (0, 30]")
        if not self.visualization_hz >= 0:
            raise ValueError(f"vda5050.visualization_hz {self.visualization_hz} must be >= 0 (0: off)")
        if not self.battery_full_v > self.battery_empty_v:
            raise ValueError("vda5050.battery_full_v must be above battery_empty_v")
