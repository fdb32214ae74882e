"""Which message type travels on which key (docs/architecture.md has the table) and what a query takes and returns."""

from __future__ import annotations

from proto import messages as m

#: topic name (after ``agv/<id>/``) -> payload type
TOPICS: dict[str, type[m.Message]] = {
    "cmd_vel": m.Twist2D,
    "safety/cmd_vel": m.Twist2D,
    "safety/state": m.SafetyState,
    "odom": m.Odometry,
    "wheels": m.WheelStates,
    "scan": m.LaserScan,
    "imu": m.Imu,
    "map": m.OccupancyGrid,
    "pose": m.PoseWithCovariance,
    "tf/map_odom": m.Transform2D,
    "particles": m.PoseArray,
    "nav/path": m.Path,
    "nav/local_plan": m.Path,
    "nav/status": m.NavStatus,
    "nav/costmap": m.OccupancyGrid,
    "clock": m.Clock,
    "sim/ground_truth": m.GroundTruth,
    "localization/nomotion/_service_event": m.ServiceEvent,
    "localization/initial_pose/_service_event": m.ServiceEvent,
    "localization/global/_service_event": m.ServiceEvent,
}

#: suffix of a query's service-event topic (``localization/nomotion`` -> ``localization/nomotion/_service_event``)
SERVICE_EVENT_SUFFIX = "/_service_event"

#: query name -> (request type, reply type)
QUERIES: dict[str, tuple[type[m.Message], type[m.Message]]] = {
    "drive/enable": (m.Empty, m.Reply),
    "drive/disable": (m.Empty, m.Reply),
    "drive/estop": (m.Empty, m.Reply),
    "drive/release": (m.Empty, m.Reply),
    "nav/goal": (m.GoalRequest, m.GoalReply),
    "nav/cancel": (m.CancelRequest, m.Reply),
    "nav/waypoints": (m.WaypointsRequest, m.GoalReply),
    "nav/waypoints/control": (m.WaypointsControl, m.Reply),
    "nav/clear_costmaps": (m.Empty, m.Reply),
    "localization/initial_pose": (m.InitialPoseRequest, m.Reply),
    "localization/global": (m.Empty, m.Reply),
    "localization/nomotion": (m.NoMotionRequest, m.LocalizationUpdate),
    "localization/save_map": (m.SaveMapRequest, m.Reply),
    "localization/mode": (m.ModeRequest, m.Reply),
    "map": (m.Empty, m.OccupancyGrid),
    "recorder/save": (m.BlackBoxSaveRequest, m.Reply),
    "sim/obstacles": (m.ObstacleRequest, m.ObstacleReply),
    "sim/teleport": (m.TeleportRequest, m.Reply),
}


def all_types() -> list[type[m.Message]]:
    """Every message type, once, in a stable order (for schema export)."""
    seen: dict[str, type[m.Message]] = {}
    for t in TOPICS.values():
        seen.setdefault(t.__name__, t)
    for req, rep in QUERIES.values():
        seen.setdefault(req.__name__, req)
        seen.setdefault(rep.__name__, rep)
    for name in dir(m):
        obj = getattr(m, name)
        if isinstance(obj, type) and issubclass(obj, m.Message) and obj is not m.Message:
            seen.setdefault(obj.__name__, obj)
    return [seen[k] for k in sorted(seen)]
