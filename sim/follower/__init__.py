"""The world follower: the SITL camera world following an external autopilot's pose (DESIGN §4).

``python -m sim.follower --autopilot udp://127.0.0.1:14550 --camera-port C --level K --seed S
--episode-json PATH --trace PATH`` listens for the autopilot's MAVLink (PX4 SITL's GCS link),
places the room at its home and heading once it is armable, renders and serves the camera at
the followed pose, and judges contact, geofence, goal and timeout (``cmnav sitl --autopilot``
runs it with the runtime).
"""

from .follower import FollowerConfig, FollowerNotReadyError, WorldFollower
from .placement import AutopilotPose, Placement, place_room
from .pose_link import AutopilotUrlError, parse_autopilot_url

__all__ = [
    "AutopilotPose",
    "AutopilotUrlError",
    "FollowerConfig",
    "FollowerNotReadyError",
    "Placement",
    "WorldFollower",
    "parse_autopilot_url",
    "place_room",
]
