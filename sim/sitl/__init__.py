"""The SITL vehicle: one simulated quadrotor behind a PX4-like MAVLink endpoint (DESIGN §4).

``python -m sim.sitl --mavlink-port P --camera-port C --level K --seed S --episode-json PATH
--trace PATH [--physics-hz 100] [--camera-hz 15] [--inject KIND@SECONDS ...] [--status-json PATH]`` builds the world ``make_worlds(K, S, 1)``,
spawns the vehicle landed below the start point (home), and serves MAVLink 2 as PX4 would
(system 1, component 1, UDP from 127.0.0.1 to 127.0.0.1:P) and camera frames (TCP
127.0.0.1:C, ``runtime.camera.sim_wire``).  It writes the episode JSON once ready and the trace
JSON on SIGTERM / SIGINT.  ``--inject`` makes it fail on purpose (``sim.sitl.faults``).

``--stand-in --pose-port Q`` makes it a stand-in for an external autopilot (PX4 SIH) in tests of
the world follower (``sim.follower``): no camera server, no room to hit (only the floor), and a
second MAVLink link to 127.0.0.1:Q with its own streams, as PX4's GCS link to 14550.
"""

from .vehicle import SitlConfig, SitlVehicle

__all__ = ["SitlConfig", "SitlVehicle"]
