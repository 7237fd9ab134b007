"""Operator commands from a viewer, as Foxglove services (no rospy): select the robot whose video
the operator watches, and set a robot's priority. Checked as the GUI's are: only a camera robot of
the fleet (or none) can be selected, only a robot of the fleet prioritised, with a priority the
manager knows; anything else is refused with the reason, which the viewer shows. Teleop stays in
our GUI: a viewer's service call cannot give its dead-man guarantees.
"""

import json
from typing import Callable, List, Tuple

from foxglove import MessageSchema, Schema, Service, ServiceSchema

from cps_fleet import names
from cps_fleet.names import absolute, in_twin

SELECT_REQUEST = {
    "type": "object",
    "properties": {"robot": {"type": "string", "description": "a camera robot, or empty for none"}},
    "required": ["robot"],
}
PRIORITY_REQUEST = {
    "type": "object",
    "properties": {"robot": {"type": "string"}, "high": {"type": "boolean", "description": "true: inspecting"}},
    "required": ["robot", "high"],
}
RESPONSE = {"type": "object", "properties": {"ok": {"type": "boolean"}, "message": {"type": "string"}}}


def _json_schema(name, schema):
    return MessageSchema(
        encoding="json", schema=Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())
    )


def _request(payload: bytes, schema: dict) -> dict:
    try:
        request = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not a JSON request: {exc}") from None
    if not isinstance(request, dict):
        raise ValueError("the request must be a JSON object")
    for key in schema["required"]:
        if key not in request:
            raise ValueError(f"the request lacks {key!r}")
    return request


class OperatorCommands:
    """The two services; `select(robot)` and `set_priority(robot, priority) -> (ok, message)` do it."""

    def __init__(
        self,
        robots,
        camera_robots,
        select: Callable[[str], None],
        set_priority: Callable[[str, int], Tuple[bool, str]],
    ):
        self.robots = list(robots)
        self.camera_robots = list(camera_robots)
        self._select = select
        self._set_priority = set_priority
        self.refused = 0

    def select_robot(self, payload: bytes) -> bytes:
        request = _request(payload, SELECT_REQUEST)
        robot = request["robot"]
        if robot != "" and robot not in self.camera_robots:
            self.refused += 1
            raise ValueError(f"{robot!r} is not a camera robot of the fleet ({', '.join(self.camera_robots)})")
        self._select(robot)
        return json.dumps({"ok": True, "message": f"selected {robot or 'none'}"}).encode()

    def set_priority(self, payload: bytes) -> bytes:
        request = _request(payload, PRIORITY_REQUEST)
        robot, high = request["robot"], request["high"]
        if robot not in self.robots or not isinstance(high, bool):
            self.refused += 1
            raise ValueError(f"robot {robot!r} (fleet: {', '.join(self.robots)}) and high (true/false: {high!r})")
        ok, message = self._set_priority(robot, 1 if high else 0)
        if not ok:
            raise ValueError(message)
        return json.dumps({"ok": True, "message": message}).encode()

    def services(self) -> List[Service]:
        return [
            _service(names.WEB_SELECT_ROBOT, "SelectRobot", SELECT_REQUEST, self.select_robot),
            _service(names.WEB_SET_PRIORITY, "SetPriority", PRIORITY_REQUEST, self.set_priority),
        ]


def _service(name, kind, request_schema, handle) -> Service:
    """A JSON service of the twin's endpoint named `name` (a WEB_* name)."""
    return Service(
        absolute(in_twin(name)),
        schema=ServiceSchema(
            f"cps_web/{kind}",
            request=_json_schema(f"cps_web/{kind}Request", request_schema),
            response=_json_schema("cps_web/Response", RESPONSE),
        ),
        handler=lambda request: handle(request.payload),
    )
