"""The VDA 5050 ``factsheet`` body from the robot config: Table 2 limits, footprint, omnidirectional kinematics."""

from __future__ import annotations

import math
from typing import Any

from services.common.robot import RobotSpec
from services.vda5050.config import Vda5050Config
from services.vda5050.core import SUPPORTED_INSTANT_ACTIONS

_ACTION_DESCRIPTIONS = {
    "cancelOrder": "stop as soon as possible and drop the order's remaining nodes and edges",
    "startPause": "stop and hold; the order resumes with stopPause",
    "stopPause": "resume the paused order",
    "initPosition": "set the localization estimate (x, y, theta in m, m, rad on mapId)",
    "stateRequest": "publish a state message now",
    "factsheetRequest": "publish the factsheet now",
}
_INIT_PARAMETERS = [{"key": "x", "valueDataType": "NUMBER"}, {"key": "y", "valueDataType": "NUMBER"},
                    {"key": "theta", "valueDataType": "NUMBER"}, {"key": "mapId", "valueDataType": "STRING"},
                    {"key": "lastNodeId", "valueDataType": "STRING", "isOptional": True}]


def factsheet(robot: RobotSpec, cfg: Vda5050Config) -> dict[str, Any]:
    """The factsheet body (without header): the chassis is a circle of ``chassis_radius_m`` around base_link."""
    r = robot.chassis_radius_m
    speed_max = math.hypot(max(robot.vx_max_mps, -robot.vx_min_mps), robot.vy_max_mps)
    polygon = [{"x": round(r * math.cos(2 * math.pi * k / 16), 4), "y": round(r * math.sin(2 * math.pi * k / 16), 4)}
               for k in range(16)]
    wheels = [{"type": "DRIVE", "isActiveDriven": True, "isActiveSteered": True,
               "position": {"x": m.x_m, "y": m.y_m}, "diameter": 0.2, "width": 0.06} for m in robot.modules]
    actions = []
    for kind in SUPPORTED_INSTANT_ACTIONS:
        entry: dict[str, Any] = {"actionType": kind, "actionDescription": _ACTION_DESCRIPTIONS[kind],
                                 "actionScopes": ["INSTANT"]}
        if kind == "initPosition":
            entry["actionParameters"] = _INIT_PARAMETERS
        actions.append(entry)
    return {
        "typeSpecification": {
            "seriesName": cfg.series_name,
            "seriesDescription": "dual-swerve omnidirectional AGV: two steered drive wheels, two casters",
            "agvKinematic": "OMNI",
            "agvClass": "CARRIER",
            "maxLoadMass": cfg.max_load_mass_kg,
            "localizationTypes": ["NATURAL"],
            "navigationTypes": ["AUTONOMOUS"],
        },
        "physicalParameters": {
            "speedMin": 0.0,
            "speedMax": round(speed_max, 4),
            "accelerationMax": max(robot.ax_max_mps2, robot.ay_max_mps2),
            "decelerationMax": max(robot.ax_max_mps2, robot.ay_max_mps2),
            "heightMax": cfg.height_max_m,
            "width": 2 * r,
            "length": 2 * r,
        },
        "protocolLimits": {
            "maxStringLens": {},
            "maxArrayLens": {"instantActions": 0},
            "timing": {"minOrderInterval": 0.0, "minStateInterval": 0.0,
                       "defaultStateInterval": cfg.state_interval_s,
                       **({"visualizationInterval": round(1.0 / cfg.visualization_hz, 4)}
                          if cfg.visualization_hz > 0 else {})},
        },
        "protocolFeatures": {
            "optionalParameters": [
                {"parameter": "order.nodes.nodePosition.allowedDeviationXy", "support": "SUPPORTED"},
                {"parameter": "order.nodes.nodePosition.allowedDeviationTheta", "support": "SUPPORTED"},
                {"parameter": "order.nodes.nodePosition.theta", "support": "SUPPORTED"},
                {"parameter": "order.edges.orientation", "support": "SUPPORTED"},
                {"parameter": "order.nodes.nodePosition", "support": "REQUIRED",
                 "description": "the vehicle plans its own path between node positions"},
            ],
            "agvActions": actions,
        },
        "agvGeometry": {
            "wheelDefinitions": wheels,
            "envelopes2d": [{"set": "chassis", "polygonPoints": polygon,
                             "description": f"circle of radius {r} m around base_link (Table 2)"}],
        },
        "loadSpecification": {"loadPositions": []},
    }
