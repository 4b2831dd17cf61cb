"""The world follower: the SITL camera world following an external autopilot's pose (DESIGN §4).

``python -m sim.follower --autopilot udp://127.0.0.1:14550 --camera-port C --level K --seed S
--episode-json PATH --trace PATH`` listens for the autopilot's MAVLink (PX4 SITL's GCS link),
places the room at its home and heading once it is armable, renders and serves the camera at
the followed pose, and judges contact, geofence, goal and timeout (``cmnav sitl --autopilot``
runs it with the runtime).

The package's modules: ``url`` (the --autopilot URL, no MAVLink), ``pose_link`` (the MAVLink pose
stream), ``placement`` (room and goal at the autopilot's home and heading), ``judge`` (contact,
geofence, goal, timeout), ``faults`` (the camera faults it injects with an external autopilot,
and why not the others) and ``follower`` (the process).  Nothing is imported here, so that the URL
check stays importable where pymavlink is absent.
"""
