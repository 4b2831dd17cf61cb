"""`cmnav fly` dry runs against the SITL vehicle through the link degraders (``sim.linkfault``):
the MAVLink link through a UDP proxy, the camera link through a TCP proxy, both scripts starting
when the vehicle first reports OFFBOARD.  Every process and proxy is stopped on the way out."""

from __future__ import annotations

import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from runtime.log.reader import FlightLogReader
from runtime.log.topics import TOPIC_COMMAND, TOPIC_DEPTH, TOPIC_OBSERVATION, TOPIC_STATE, TOPIC_TIMING, TOPIC_WATCHDOG
from sim.linkfault import Impairment, StreamFault, TcpLinkProxy, UdpLinkProxy
from sim.sitl_session import free_port
from tests.e2e.fly_helpers import NotifyListener, Sitl, finish_fly, fly_config, start_fly

# Longer than any flight here (start-up, take-off, a 20 s episode, landing): the proxies outlive
# the flight and still stop by themselves if a test forgets them.
LINK_LIFETIME_S = 150.0
EPISODE_TIMEOUT_S = 20.0


@dataclass
class LinkFlight:
    """What one degraded dry run left: exit code, summary, runtime log text, the stopped vehicle,
    the proxies (their stats and script clocks)."""

    code: int
    summary: dict
    log_text: str
    sitl: Sitl
    mavlink: UdpLinkProxy
    camera: TcpLinkProxy

    @property
    def episode(self) -> dict:
        (episode,) = self.summary["episodes"]
        return episode


def fly_degraded(model: Path, tmp_path: Path, impairments: Sequence[Impairment] = (),
                 stream_faults: Sequence[StreamFault] = (), seed: int = 0) -> LinkFlight:  # fmt: skip
    """One `cmnav fly` dry run (arm, take off, offboard, fly half way to the world's goal, land)
    with the links degraded as scripted (times from the vehicle's OFFBOARD entry)."""
    runtime_port = free_port(socket.SOCK_DGRAM)
    vehicle: list[Sitl] = []

    def offboard() -> bool:
        return bool(vehicle) and "OFFBOARD" in vehicle[0].modes()

    mavlink = UdpLinkProxy(runtime_port, impairments, seed=seed, lifetime_s=LINK_LIFETIME_S, start_when=offboard)
    camera: TcpLinkProxy | None = None
    notify: NotifyListener | None = None
    sitl: Sitl | None = None
    try:
        sitl = Sitl(tmp_path, mavlink.port)
        vehicle.append(sitl)
        camera = TcpLinkProxy(sitl.camera_port, stream_faults, lifetime_s=LINK_LIFETIME_S, start_when=offboard)
        notify = NotifyListener(tmp_path / "notify")
        gx, gy, gz = sitl.episode["goal_rel_home_enu_m"]
        mission = (f"allow_arm_takeoff = true\ntakeoff_alt_m = {sitl.episode['takeoff_alt_m']:.3f}\nmax_episodes = 1")
        config = fly_config(model, runtime_port, camera.port, [gx / 2.0, gy / 2.0, gz], tmp_path / "logs", mission)
        config = config.replace("episode_timeout_s = 30.0", f"episode_timeout_s = {EPISODE_TIMEOUT_S}")
        code, summary = finish_fly(start_fly(tmp_path, config, notify), tmp_path)
    finally:
        for closer in (sitl.stop if sitl else None, notify.close if notify else None,
                       camera.close if camera else None, mavlink.close):  # fmt: skip
            if closer is not None:
                closer()
    return LinkFlight(code, summary, (tmp_path / "fly.log").read_text(), sitl, mavlink, camera)


@dataclass
class LoggedEpisode:
    """What the flight log says happened, on the runtime's monotonic clock (ns).

    ``frames_ns``: capture times of the valid frames the loop used; ``trips``: (log time, event
    record) of each watchdog trip; ``t_start_ns``: supervision start; ``sent``: one
    ``(t_step_started_ns, t_cmd_ns, state_age_ms)`` per policy command sent, where the state age
    (step start - receipt of the position it was computed from) is known when the step's position
    is one the state log also recorded (every position held longer than a state-log period is);
    ``stopped_early``: why the log ended before its footer (None: complete)."""

    t_start_ns: int
    frames_ns: list[int]
    trips: list[tuple[int, dict]]
    holds: list[tuple[int, dict]]
    sent: list[tuple[int, int, float | None]]
    stopped_early: str | None


def read_episode(path: str | Path) -> LoggedEpisode:
    reader = FlightLogReader(path)
    posvel_rx_ns: dict[tuple, int] = {}
    observations: dict[int, dict] = {}
    timings: dict[int, dict] = {}
    commands: list[tuple[int, dict]] = []
    frames, trips, holds, t_start = [], [], [], 0
    topics = (TOPIC_DEPTH, TOPIC_STATE, TOPIC_OBSERVATION, TOPIC_COMMAND, TOPIC_TIMING, TOPIC_WATCHDOG)
    for topic, log_time, message in reader.messages(topics):
        t_ns = log_time - reader.offset_ns
        if topic == TOPIC_DEPTH:
            frames.append(t_ns)
        elif topic == TOPIC_STATE:
            posvel_rx_ns.setdefault(tuple(message["pos_enu_m"]), message["t_posvel_ns"])
        elif topic == TOPIC_OBSERVATION:
            observations[message["frame_seq"]] = message
        elif topic == TOPIC_TIMING:
            timings[message["frame_seq"]] = message
        elif topic == TOPIC_COMMAND and message["source"] == "policy" and message["sent"]:
            commands.append((t_ns, message))
        elif topic == TOPIC_WATCHDOG:
            if message["event"] == "start":
                t_start = t_ns
            elif message["event"] == "trip":
                trips.append((t_ns, message))
            elif message["event"] == "hold":
                holds.append((t_ns, message))
    sent = []
    for t_cmd, command in commands:
        seq = command["frame_seq"]
        observation, timing = observations.get(seq), timings.get(seq)
        if observation is None or timing is None:
            continue
        t_step = observation["t_capture_ns"] + int(timing["stages_ms"]["frame_age_at_step"] * 1e6)
        t_rx = posvel_rx_ns.get(tuple(observation["pos_enu_m"]))
        sent.append((t_step, t_cmd, None if t_rx is None else (t_step - t_rx) / 1e6))
    return LoggedEpisode(t_start, sorted(frames), trips, holds, sent, reader.stopped_early)
