"""Message types that cross a process boundary (docs/architecture.md).

Conventions:
- SI units everywhere: metres (m), radians (rad), seconds (s), m/s, rad/s, amperes (A).
- ``stamp`` is seconds on the publishing service's clock (sim time when ``use_sim_time``).
- ``frame`` strings follow REP-105: ``map``, ``odom``, ``base_link``, ``laser``.
- Angles follow REP-103: counter-clockwise positive, 0 rad along +x.
- Large arrays travel as raw little-endian bytes; ``ARRAY_FIELDS`` names their numpy dtype and
  shape so that ``numpy.frombuffer`` reads them without a copy (see ``proto.arrays``).
"""

from __future__ import annotations

import re
from typing import ClassVar, Literal

import msgspec


class Message(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Base of every message. ``ARRAY_FIELDS`` maps a bytes field to (dtype, columns)."""

    ARRAY_FIELDS: ClassVar[dict[str, tuple[str, int]]] = {}


# --------------------------------------------------------------------------- geometry


class Pose2D(Message):
    """A planar pose: position x, y in m and heading theta in rad (in the frame of the carrier)."""

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0


class Twist2D(Message):
    """A body-frame velocity: vx, vy in m/s, wz in rad/s. ``stamp`` in s (0 when unset)."""

    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    stamp: float = 0.0


class Transform2D(Message):
    """Pose of ``child`` in ``parent`` (e.g. map -> odom): x, y in m, theta in rad."""

    stamp: float = 0.0
    parent: str = "map"
    child: str = "odom"
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0


LocalizationState = Literal["localizing", "tracking", "lost"]


class PoseWithCovariance(Message):
    """Pose in ``frame`` with its 3x3 covariance over (x [m], y [m], theta [rad]), row-major.

    ``state`` is the filter's own verdict: ``localizing`` until it has converged (at start, after a global
    relocalization), ``tracking`` while the scans fit the map, ``lost`` once they stop fitting. ``match_score`` is the
    fraction of scan beams that the map explains (0..1) and ``spread_m`` the particle cloud's position spread; both are
    the inputs of that verdict. Consumers must not act on a pose whose state is not ``tracking``.

    ``position_std_m`` is how well the position is known along its weakest direction (``weakest_axis_rad`` in this
    frame) and ``heading_std_rad`` the heading's: odometry drift grown while driving, shrunk only by what the scans
    constrain (services/localization/uncertainty.py). Unlike the particle ``covariance`` it grows along a corridor
    the scans do not pin. 0: not provided.
    """

    stamp: float = 0.0
    frame: str = "map"
    pose: Pose2D = msgspec.field(default_factory=Pose2D)
    covariance: list[float] = msgspec.field(default_factory=lambda: [0.0] * 9)
    state: LocalizationState = "tracking"
    match_score: float = 1.0
    spread_m: float = 0.0
    position_std_m: float = 0.0
    weakest_axis_rad: float = 0.0
    heading_std_rad: float = 0.0


class PoseArray(Message):
    """Poses as float32 rows (x [m], y [m], theta [rad]); optional float32 weights, one per pose."""

    ARRAY_FIELDS: ClassVar[dict[str, tuple[str, int]]] = {"poses": ("<f4", 3), "weights": ("<f4", 1)}

    stamp: float = 0.0
    frame: str = "map"
    poses: bytes = b""
    weights: bytes = b""


class Path(Message):
    """A path as float32 rows (x [m], y [m], theta [rad]) in ``frame``."""

    ARRAY_FIELDS: ClassVar[dict[str, tuple[str, int]]] = {"poses": ("<f4", 3)}

    stamp: float = 0.0
    frame: str = "map"
    poses: bytes = b""


# --------------------------------------------------------------------------- drive


class Odometry(Message):
    """Pose of ``child_frame`` in ``frame`` plus body twist; covariances 3x3 row-major over (x, y, theta)."""

    stamp: float = 0.0
    frame: str = "odom"
    child_frame: str = "base_link"
    pose: Pose2D = msgspec.field(default_factory=Pose2D)
    twist: Twist2D = msgspec.field(default_factory=Twist2D)
    pose_covariance: list[float] = msgspec.field(default_factory=lambda: [0.0] * 9)
    twist_covariance: list[float] = msgspec.field(default_factory=lambda: [0.0] * 9)


class ModuleState(Message):
    """One swerve module: measured steer angle (rad) and wheel speed (m/s), currents (A), raw counts, flags.

    ``fault_flags`` / ``status_flags`` are the RoboteQ FF / FS bit fields (protocols.md §1.7); ``battery_v`` is the
    controller's battery voltage (V, object 0x210D.2; 0 until reported).
    """

    steer_rad: float = 0.0
    speed_mps: float = 0.0
    steer_cmd_rad: float = 0.0
    speed_cmd_mps: float = 0.0
    traction_amps: float = 0.0
    steer_amps: float = 0.0
    traction_counts: int = 0
    steer_counts: int = 0
    fault_flags: int = 0
    status_flags: int = 0
    battery_v: float = 0.0


class WheelStates(Message):
    """Drive state: per-module states, the FK least-squares residual (m/s, a slip indicator), loop stats."""

    stamp: float = 0.0
    modules: list[ModuleState] = msgspec.field(default_factory=list)
    slip_residual_mps: float = 0.0
    enabled: bool = False
    estopped: bool = False
    link_ok: bool = False
    fault: str = ""
    loop_hz: float = 0.0
    loop_jitter_p99_ms: float = 0.0
    loop_overruns: int = 0


class Imu(Message):
    """Orientation as yaw/pitch/roll (rad), angular velocity (rad/s) and linear acceleration (m/s^2) in ``frame``."""

    stamp: float = 0.0
    frame: str = "imu"
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    angular_velocity: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    linear_acceleration: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])


# --------------------------------------------------------------------------- lidar


class LaserScan(Message):
    """A planar scan (REP-103 angles, rad). Beam i is at angle_min + i*angle_increment.

    ``ranges`` are float32 m (+inf: no return, as ROS drivers report); ``intensities`` float32 or empty.
    ``mount`` is the laser's pose in base_link.
    """

    ARRAY_FIELDS: ClassVar[dict[str, tuple[str, int]]] = {"ranges": ("<f4", 1), "intensities": ("<f4", 1)}

    stamp: float = 0.0
    frame: str = "laser"
    angle_min: float = 0.0
    angle_max: float = 0.0
    angle_increment: float = 0.0
    time_increment: float = 0.0
    scan_time: float = 0.0
    range_min: float = 0.0
    range_max: float = 0.0
    ranges: bytes = b""
    intensities: bytes = b""
    mount: Pose2D = msgspec.field(default_factory=Pose2D)
    scan_counter: int = 0


# --------------------------------------------------------------------------- maps


class OccupancyGrid(Message):
    """Row-major int8 cells (row 0 at ``origin``, +x along a row): -1 unknown, 0 free .. 100 occupied.

    ``resolution`` in m/cell; ``origin`` is the pose of cell (0, 0)'s outer corner in ``frame``.
    """

    ARRAY_FIELDS: ClassVar[dict[str, tuple[str, int]]] = {"data": ("<i1", 1)}

    stamp: float = 0.0
    frame: str = "map"
    resolution: float = 0.05
    width: int = 0
    height: int = 0
    origin: Pose2D = msgspec.field(default_factory=Pose2D)
    data: bytes = b""


# --------------------------------------------------------------------------- nav

NavState = Literal["idle", "planning", "driving", "rotating", "recovering", "succeeded", "failed", "canceled"]


class WaypointResult(Message):
    """Outcome of one waypoint in a sequence: final pose error (m, m, rad) and time (s)."""

    id: str = ""
    reached: bool = False
    skipped: bool = False
    error: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    time_s: float = 0.0
    reason: str = ""


class NavStatus(Message):
    """Navigation state. ``error`` names the failure reason when state is ``failed``."""

    stamp: float = 0.0
    state: NavState = "idle"
    goal_id: str = ""
    goal: Pose2D | None = None
    distance_left_m: float = 0.0
    error: str = ""
    recoveries: int = 0
    sequence_id: str = ""
    waypoint_index: int = -1
    waypoint_count: int = 0
    sequence_paused: bool = False
    waypoint_results: list[WaypointResult] = msgspec.field(default_factory=list)


# --------------------------------------------------------------------------- safety


SafetyAction = Literal["clear", "slowdown", "approach", "stop", "no_scan"]


class SafetyState(Message):
    """The collision monitor's verdict on the last command (between ``cmd_vel`` and ``safety/cmd_vel``).

    ``action``: ``clear`` (passed unchanged), ``slowdown`` (an obstacle inside the slow-down zone ahead: translation
    scaled by ``scale``), ``approach`` (contact predicted within the look-ahead time: scaled by ``scale``), ``stop``
    (an obstacle inside the stop zone ahead: translation zeroed), ``no_scan`` (no fresh scan: everything zeroed).
    ``nearest_m`` is the clearance between the footprint and the nearest scan point ahead (-1 when none),
    ``requested``/``commanded`` the twists in and out, ``interventions`` a running count of commands changed.
    """

    stamp: float = 0.0
    action: SafetyAction = "clear"
    scale: float = 1.0
    nearest_m: float = -1.0
    reason: str = ""
    requested: Twist2D = msgspec.field(default_factory=Twist2D)
    commanded: Twist2D = msgspec.field(default_factory=Twist2D)
    interventions: int = 0


# --------------------------------------------------------------------------- sim


class Clock(Message):
    """Simulated time (s) and the speed factor the simulator runs at (sim s per wall s)."""

    stamp: float = 0.0
    speed_factor: float = 1.0


class GroundTruth(Message):
    """True robot pose in the world (map) frame and true body twist; ``collided`` once it hits the world or another
    robot (latched until a teleport), ``contact_with`` what it touched: ``"wall"`` or the other robot's id."""

    stamp: float = 0.0
    pose: Pose2D = msgspec.field(default_factory=Pose2D)
    twist: Twist2D = msgspec.field(default_factory=Twist2D)
    collided: bool = False
    contact_with: str = ""


ServiceEventType = Literal["request_received", "response_sent"]


class ServiceEvent(Message):
    """One step of a query as the service answering it saw it, published on ``<query>/_service_event`` (rosbag2's
    service introspection, service_msgs/ServiceEventInfo) so that a recording holds the requests a service acted on
    and ``zagv replay`` can issue them again. ``request_received``: the request has taken effect (``request``: its
    msgpack payload); ``response_sent``: the answer (``response``), served on the message of topic ``input_topic``
    stamped ``input_stamp`` (s) (``localization/nomotion``: the scan the update ran on; empty and 0: none).
    ``stamp``: the service's clock (s); ``sequence`` pairs the two events of one request."""

    stamp: float
    event: ServiceEventType
    sequence: int
    request: bytes = b""
    response: bytes = b""
    input_topic: str = ""
    input_stamp: float = 0.0


# --------------------------------------------------------------------------- queries


class Empty(Message):
    """A request with no arguments."""


class Reply(Message):
    """The generic explicit result of a query: ``ok`` and a human-readable ``message`` (the reason when not ok)."""

    ok: bool
    message: str = ""


class LocalizationUpdate(Message):
    """The answer to ``localization/nomotion``, sent once the update it asked for has run on a scan (or could not):
    ``ok`` and a human-readable ``message``; with ``ok``, the updated estimate (``pose``, stamped with its scan) and
    the ``map_odom`` transform derived from it, exactly as published on ``pose`` and ``tf/map_odom``. A client that
    judges the robot's pose after the update applies these first, whatever order the topics arrive in."""

    ok: bool
    message: str = ""
    pose: PoseWithCovariance | None = None
    map_odom: Transform2D | None = None


class GoalRequest(Message):
    """A navigation goal in ``frame``; ``id`` is chosen by the caller or assigned by nav."""

    pose: Pose2D
    id: str = ""
    frame: str = "map"


class GoalReply(Message):
    """Whether a goal (or sequence) was accepted, its id, and the reason when rejected."""

    accepted: bool
    goal_id: str = ""
    reason: str = ""


class CancelRequest(Message):
    """Cancel the goal with ``goal_id`` (empty: whatever is active)."""

    goal_id: str = ""


class Waypoint(Message):
    """One pose of a waypoint sequence."""

    pose: Pose2D
    id: str = ""


class WaypointsRequest(Message):
    """Run ``waypoints`` in order (continuous navigation)."""

    waypoints: list[Waypoint]
    id: str = ""


class WaypointsControl(Message):
    """Control the running sequence."""

    action: Literal["pause", "resume", "skip", "cancel"]


class InitialPoseRequest(Message):
    """Set the localization estimate: pose in map, with a 3x3 covariance (empty: filter defaults).
    ``at_scan_stamp`` (s): 0 sets it at once; else just before the filter runs on the first scan stamped at or after
    it (``zagv replay`` sets the stamp of the scan a recorded request was served on, so that the replayed filter is
    re-initialised on the same scan as the live one, whatever scans are still on their way when the request comes)."""

    pose: Pose2D
    covariance: list[float] = msgspec.field(default_factory=list)
    at_scan_stamp: float = 0.0
    #: when the pose was given (s, robot clock; 0: when the request arrives): scans stamped before it show the robot
    #: before it was placed there and are ignored (ROS initialpose's header stamp); a replay sets the recorded one
    stamp: float = 0.0


class NoMotionRequest(Message):
    """Update the localization filter without motion and refine at rest (``localization/nomotion``).
    ``at_scan_stamp`` (s): 0 runs it on the next scan the filter takes after the ones already waiting; else on the
    first scan stamped at or after it (``zagv replay``: the scan a recorded request ran on). An ``Empty`` request
    encodes as this one's defaults."""

    at_scan_stamp: float = 0.0


#: a map name ``localization/save_map`` accepts: 1-64 letters, digits, '_', '-' or '.', no path, not starting with
#: '.' or '-'. ``\Z``, not ``$``: ``$`` also matches before a trailing newline.
MAP_NAME = re.compile(r"\A[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}\Z")


class SaveMapRequest(Message):
    """Save the current map as ``<name>.yaml`` + ``<name>.pgm`` in the maps folder."""

    name: str


class ModeRequest(Message):
    """Switch localization between SLAM (``mapping``) and AMCL (``navigation``, on ``map_yaml`` if given)."""

    mode: Literal["mapping", "navigation"]
    map_yaml: str = ""


class BlackBoxSaveRequest(Message):
    """Save the black box (the rolling recording of the last minutes) now; ``reason`` names the bag."""

    reason: str = "on-demand"


class ObstacleRequest(Message):
    """Add (or remove, by id) a rectangular obstacle [xmin, ymin, xmax, ymax] (m) in the sim world."""

    action: Literal["add", "remove", "clear"]
    id: str = ""
    rect: list[float] = msgspec.field(default_factory=list)


class ObstacleReply(Message):
    """Result of an obstacle change, with the current obstacle ids."""

    ok: bool
    message: str = ""
    ids: list[str] = msgspec.field(default_factory=list)


class TeleportRequest(Message):
    """Move the simulated robot to ``pose`` instantly (kidnapping tests)."""

    pose: Pose2D
