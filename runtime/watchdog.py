"""The safety watchdog (DESIGN §3): detects faults in flight and puts the vehicle in a safe state.

MAVSDK re-sends the last setpoint at 20 Hz by itself, so a stalled loop would keep the vehicle
flying on a stale command; the watchdog checks independently of the policy task.  Trips:
stale frame (or only bad frames: no valid frame for as long), step over its trip limit (or
hung), NaN/Inf action, stale telemetry, pilot left offboard, depth invalid fraction above a
limit for too long, geofence (horizontal distance from where supervision started, height band
above home; a goal outside it is refused when the episode starts); and the outcome: the vehicle
not following its velocity commands (``tracking``: error above a bound for longer than a window,
``runtime.tracking``), tilted past a flip/tumble bound (``attitude``), or the autopilot's own word
(``vehicle_fault``: a STATUSTEXT of severity CRITICAL or worse, or a disarm in flight).  Before
supervision, a refused start (offboard refused by the autopilot) is recorded with
:meth:`Watchdog.refuse_start`.

Response to a trip: a zero-velocity (hover) setpoint at once, then the brake's setpoint at the
control rate (:func:`brake_setpoint`: against the measured velocity), then ``offboard.stop()``
(PX4 Hold) once the vehicle has braked (:func:`brake_ended`: at least ``hold_grace_s``, then the
measured speed below ``brake_speed_m_s``, or ``brake_timeout_s`` at the latest).  Pilot left offboard: the runtime stops commanding at once and
sends nothing more (no Hold either: the pilot has the vehicle).  Every trip is logged and
recorded as ``{cause, detail, t_s, detect_ms, response, hold_t_s}`` (and sent to ``on_event``
with ``event`` = "trip", then again with "hold" once Hold was commanded) where ``t_s`` is seconds since
supervision started and ``detect_ms`` is the time from the moment the trip condition became
true (threshold crossed, or the evidence received) to the trip.

Time-based checks run in :meth:`Watchdog.tick` (the watchdog task calls it every ``period_s``);
the action check runs in :meth:`Watchdog.check_action`, called by the policy task before it
sends each command.  All times are ``time.monotonic_ns`` values passed in, so tests drive it
with a fake clock.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import asdict, dataclass
from enum import Enum
from typing import Callable

import numpy as np

from .command_gate import CommandGate
from .contract import HOVER, CONTROL_PERIOD_S, VelocityBodyYawspeed, velocity_flu_to_mavsdk
from .contract.frames import world_enu_to_vehicle
from .camera.surfaces import SeenSurfaces, nearest_m
from .config import WatchdogConfig
from .tracking import OverBound, TrackingMonitor, TrackingStatus, tilt_rad
from .state import MODE_OFFBOARD, VehicleError, VehicleState

log = logging.getLogger(__name__)

_NS_PER_MS = 1_000_000
_NS_PER_S = 1_000_000_000


class TripCause(str, Enum):
    STALE_FRAME = "stale_frame"
    BAD_FRAMES = "bad_frames"  # frames kept coming, but none fit to fly on
    STEP_DEADLINE = "step_deadline"
    BAD_ACTION = "bad_action"
    STALE_TELEMETRY = "stale_telemetry"
    PILOT_LEFT_OFFBOARD = "pilot_left_offboard"
    DEPTH_INVALID = "depth_invalid"
    GEOFENCE = "geofence"
    POLICY_ERROR = "policy_error"
    OFFBOARD_REFUSED = "offboard_refused"
    TRACKING = "tracking"  # the vehicle does not follow its velocity commands
    ATTITUDE = "attitude"  # tilted past tilt_max_deg: flipped or tumbling
    VEHICLE_FAULT = "vehicle_fault"  # the autopilot says so: CRITICAL STATUSTEXT, disarmed in flight
    # The autopilot left offboard by itself after the link was down longer than its
    # COM_OF_LOSS_T (watchdog.offboard_loss_s): its failsafe has the vehicle, not a pilot.
    OFFBOARD_LOSS_FAILSAFE = "offboard_loss_failsafe"
    # The simulated world says the vehicle touched something (SITL camera link, frame meta
    # "contact"): an external autopilot in SITL flies on through the room it cannot see.
    SIM_CONTACT = "sim_contact"


class Response(str, Enum):
    HOVER_THEN_HOLD = "hover_then_hold"
    STOP_COMMANDING = "stop_commanding"
    ALREADY_TRIPPED = "already_tripped"
    HOLD = "hold"  # offboard never started: nothing to hover, Hold (stay in it) at once
    VEHICLE_FAILSAFE = "vehicle_failsafe"  # the autopilot's failsafe has the vehicle: send nothing more


@dataclass
class Trip:
    cause: TripCause
    detail: str
    t_ns: int
    detect_ms: float
    response: Response
    hold_t_ns: int | None = None

    def record(self, t0_ns: int) -> dict:
        """JSON-ready record; times in seconds since ``t0_ns``."""
        return {
            "cause": self.cause.value,
            "detail": self.detail,
            "t_s": round((self.t_ns - t0_ns) / _NS_PER_S, 4),
            "detect_ms": round(self.detect_ms, 3),
            "response": self.response.value,
            "hold_t_s": None if self.hold_t_ns is None else round((self.hold_t_ns - t0_ns) / _NS_PER_S, 4),
        }


@dataclass(frozen=True)
class WatchInputs:
    """What the periodic check looks at (times: ns, CLOCK_MONOTONIC; 0 = never)."""

    now_ns: int
    t_last_frame_capture_ns: int  # the newest *valid* frame
    t_step_started_ns: int  # the step in progress (frame taken), 0 = no step running
    vehicle: VehicleState
    frames_rejected: int = 0  # frames refused as unfit since that valid frame
    last_rejection: str = ""  # why the last of them was refused


def brake_ended(vehicle: VehicleState, t_brake_ns: int, now_ns: int, config: WatchdogConfig) -> str | None:
    """Whether the brake that began at ``t_brake_ns`` (zero-velocity setpoint sent) may end and Hold
    follow: "stopped" (braked at least ``hold_grace_s`` and the speed measured since is below
    ``brake_speed_m_s``), "brake_timeout" (braked ``brake_timeout_s``, stopped or not: stale or
    missing telemetry cannot hold the vehicle in offboard for ever), None (keep braking).

    The speed is the norm of the world-ENU velocity, trusted only when it was received after the
    brake began and within ``telemetry_stale_ms``."""
    braked_ns = now_ns - t_brake_ns
    if braked_ns >= config.brake_timeout_s * _NS_PER_S:
        return "brake_timeout"
    if braked_ns < config.hold_grace_s * _NS_PER_S:
        return None
    fresh = vehicle.t_posvel_ns > t_brake_ns and now_ns - vehicle.t_posvel_ns <= config.telemetry_stale_ms * _NS_PER_MS
    if fresh and measured_speed_m_s(vehicle) < config.brake_speed_m_s:
        return "stopped"
    return None


def brake_setpoint(vehicle: VehicleState, now_ns: int, config: WatchdogConfig) -> VelocityBodyYawspeed:
    """The brake's setpoint: ``-brake_gain`` x the measured velocity in the body frame (its norm at
    most ``brake_setpoint_max_m_s``, no yaw rate), so the autopilot's controller is asked to
    decelerate as hard as its limits allow instead of being left to its own integrator; a
    zero-velocity setpoint when the velocity is stale (older than ``telemetry_stale_ms``) or
    unknown, or with ``brake_gain`` 0."""
    fresh = vehicle.t_posvel_ns > 0 and now_ns - vehicle.t_posvel_ns <= config.telemetry_stale_ms * _NS_PER_MS
    vel_body = vehicle.vel_body_flu_m_s
    if config.brake_gain == 0.0 or not fresh or not np.all(np.isfinite(vel_body)):
        return HOVER
    setpoint = -config.brake_gain * vel_body
    norm = float(np.linalg.norm(setpoint))
    if norm > config.brake_setpoint_max_m_s:
        setpoint = setpoint * (config.brake_setpoint_max_m_s / norm)
    return velocity_flu_to_mavsdk(np.array([setpoint[0], setpoint[1], setpoint[2], 0.0]))


# The dry run's landing after its last goal (``mission.land_in_offboard``): PX4's Land, commanded
# while the vehicle still moved, carried it 0.2-1 m sideways while it descended on PX4 SIH, into
# obstacles beside the goal (docs/px4-sitl.md §8).  The runtime descends in offboard instead,
# holding horizontally the position estimate where the landing began, until the autopilot reports
# the touch-down, and leaves the disarm to the autopilot's land detector.  (Holding the corrected
# velocity at zero instead, the brake's law, left the velocity estimate's residual error to
# integrate: 0.30 m of true drift at the median, 0.74 m at most, in 53 PX4 landings.)
LAND_DESCENT_M_S = 0.5  # PX4's land detector needs a commanded descent >= 1.1 x LNDMC_Z_VEL_MAX (0.25 m/s)
# Beyond height / LAND_DESCENT_M_S until the touch-down is reported: PX4 SIH's land detector took
# 3.8 s after 2.9 s of descent from 1.5 m (its maybe-landed and landed stages).
LAND_DESCENT_TIME_MARGIN_S = 8.0
LAND_DESCENT_UNKNOWN_HEIGHT_M = 5.0  # the height assumed when the autopilot has reported no home
LAND_DISARM_WAIT_S = 4.0  # after the touch-down report, for the autopilot's own disarm (PX4: COM_DISARM_LAND, 2 s)


LAND_HOLD_GAIN_PER_S = 1.0  # horizontal velocity per metre from the held point (PX4's MPC_XY_P: 0.95)
# Horizontal command limit while landing (and climbing after the take-off).  At 0.3 m/s it held
# the hold's command at the limit for 20-48 % of the descent in 33 of 81 PX4 SIH landings, and the
# estimate's drift grew with that share (correlation 0.88): PX4's velocity estimate disagreed with
# its position by more than the limit while it descended.  At 0.5 m/s the true drift was median
# 0.30 / p90 0.57 / max 0.67 m (89 landings of default-way2) against 0.31 / 0.59 / 0.71 at 0.3
# (57 of default-site): the limit was not what let it drift; what does is PX4's estimate.
LAND_HOLD_MAX_M_S = 0.5

# The dry run's take-off: PX4 ends its take-off in Hold up to NAV_MC_ALT_RAD (0.8 m) below the
# height asked (0.65-0.74 m short on PX4 v1.16 SIH) and then climbs the rest in Hold slowly while
# its position hold wanders (17 s and 1.5 m of true drift seen, into a side wall once).  The
# runtime takes the vehicle from that Hold and climbs the rest in offboard, holding its position
# estimate as the landing does (``FlightLoop.climb``).
TAKEOFF_HOLD_SHORT_M = 1.0  # Hold in the air this far below the height asked ends the autopilot's take-off
TAKEOFF_CLIMB_MAX_M_S = 0.5
TAKEOFF_CLIMB_GAIN_PER_S = 1.0  # climb speed per metre still to go
TAKEOFF_CLIMB_REACHED_M = 0.1  # within this of the height asked: the climb is done
TAKEOFF_CLIMB_TIME_MARGIN_S = 5.0  # beyond (height to go) / TAKEOFF_CLIMB_MAX_M_S


def hold_setpoint(vehicle: VehicleState, hold_enu_m: np.ndarray, up_m_s: float, now_ns: int, config: WatchdogConfig) -> VelocityBodyYawspeed:
    """The landing's and the take-off climb's setpoint: horizontally back toward ``hold_enu_m``
    (local ENU m, the position estimate where the manoeuvre began) at ``LAND_HOLD_GAIN_PER_S`` per
    metre (its norm at most ``LAND_HOLD_MAX_M_S``), no yaw rate, and ``up_m_s`` vertically (+ up);
    zero horizontally when the estimate is stale (older than ``telemetry_stale_ms``) or unknown."""
    fresh = vehicle.t_posvel_ns > 0 and now_ns - vehicle.t_posvel_ns <= config.telemetry_stale_ms * _NS_PER_MS
    error_enu = np.asarray(hold_enu_m, dtype=np.float64)[:2] - vehicle.pos_enu_m[:2]
    if not fresh or not np.all(np.isfinite(error_enu)) or not math.isfinite(vehicle.yaw_enu_rad):
        return dataclasses.replace(HOVER, down_m_s=-up_m_s)
    horizontal = LAND_HOLD_GAIN_PER_S * error_enu
    norm = float(np.linalg.norm(horizontal))
    if norm > LAND_HOLD_MAX_M_S:
        horizontal *= LAND_HOLD_MAX_M_S / norm
    forward, left = world_enu_to_vehicle(np.array([*horizontal, 0.0]), vehicle.yaw_enu_rad)[:2]
    return velocity_flu_to_mavsdk(np.array([forward, left, up_m_s, 0.0]))


def climb_speed_m_s(height_to_go_m: float) -> float:
    """The take-off climb's vertical speed (m/s, up) with ``height_to_go_m`` still to climb:
    proportional, at most ``TAKEOFF_CLIMB_MAX_M_S``, never down (an unknown height: none)."""
    if not math.isfinite(height_to_go_m):
        return 0.0
    return min(max(TAKEOFF_CLIMB_GAIN_PER_S * height_to_go_m, 0.0), TAKEOFF_CLIMB_MAX_M_S)


def descent_time_limit_s(vehicle: VehicleState) -> float:
    """How long the descent may take until the touch-down is reported: its height at
    ``LAND_DESCENT_M_S`` plus the margin."""
    height_m = vehicle.height_above_home_m
    if not math.isfinite(height_m):
        height_m = LAND_DESCENT_UNKNOWN_HEIGHT_M
    return max(height_m, 0.0) / LAND_DESCENT_M_S + LAND_DESCENT_TIME_MARGIN_S


# Landing clear of what lay ahead (docs/px4-sitl.md §8): after the goal a dry run flies back along
# the path it came by (free: it was just flown) before its landing, slowly, at the height it stopped.
RETREAT_SPEED_M_S = 0.5  # the reference point's speed back along the path
RETREAT_POSITION_GAIN_PER_S = 1.0  # velocity per metre between the vehicle and the reference (PX4's MPC_XY_P: 0.95)
RETREAT_INTEGRAL_GAIN_PER_S2 = 0.3  # ... and per metre-second of it: cancels a biased velocity estimate
RETREAT_INTEGRAL_MAX_M_S = 0.8  # the integral term's largest velocity (no wind-up)
RETREAT_MAX_SPEED_M_S = 1.0  # horizontal command limit
RETREAT_ARRIVED_M = 0.15  # horizontal distance to the path's end that counts as arrived
# Near the path's end the horizontal command is at most sqrt(2 * this * distance to the end): the
# vehicle arrives slowly instead of at the integral's speed (on PX4 SIH it came in at 0.8 m/s and
# coasted on past the end into an obstacle beside the path flown: 2 of 40 flights at levels 3 / 6).
RETREAT_APPROACH_DECEL_M_S2 = 0.4
RETREAT_CLIMB_GAIN_PER_S = 1.0  # vertical speed per metre of height error
RETREAT_CLIMB_MAX_M_S = 0.3


def retreat_path(flown_enu_m: np.ndarray, distance_m: float) -> np.ndarray:
    """The flown path (positions in order, world ENU m, shape (N, 3)) walked backwards from its end
    for ``distance_m`` of horizontal length: newest point first (:func:`cut_path`)."""
    return cut_path(np.asarray(flown_enu_m, dtype=np.float64)[::-1], distance_m)


def cut_path(path_enu_m: np.ndarray, distance_m: float) -> np.ndarray:
    """The polyline ``path_enu_m`` (N, 3) walked from its first point for ``distance_m`` of
    horizontal length, the last point interpolated where the length is reached (all of it if it is
    shorter; its first point alone for a length <= 0)."""
    points = np.asarray(path_enu_m, dtype=np.float64)
    if len(points) < 2 or distance_m <= 0.0:
        return points[:1].copy()
    walked_m = arc_lengths_m(points)
    if walked_m[-1] <= distance_m:
        return points.copy()
    i = int(np.searchsorted(walked_m, distance_m))  # walked_m[i - 1] < distance_m <= walked_m[i]
    return np.vstack([points[:i], path_point(points, walked_m, distance_m)])


class RetreatTracker:
    """Follows a reference point that moves along ``path`` (from :func:`landing_way`) at
    ``RETREAT_SPEED_M_S``: velocity = the reference's own + a P term on the horizontal distance to
    it (limited to ``RETREAT_MAX_SPEED_M_S``, and near the path's end to what stops there at
    ``RETREAT_APPROACH_DECEL_M_S2``), vertical speed toward its height.

    With ``integral`` an integral term on that distance is added: PX4's velocity estimate can be
    off from the truth by 0.3-0.7 m/s at these speeds (SIH, measured: the estimate's position moved
    1.2 m the other way while its velocity said 0.35 m/s toward the target), so a velocity command
    alone can leave the vehicle drifting the wrong way; the integral commands what it takes.  The
    runtime turns it off where it corrects that error itself (``runtime.tracking.VelocityBias``): there it
    only winds up on the autopilot's lag and carries the vehicle past the end."""

    def __init__(self, path_enu_m: np.ndarray, integral: bool = True) -> None:
        self.path = np.asarray(path_enu_m, dtype=np.float64)
        self.integral = integral  # off where the runtime corrects the velocity estimate (runtime.tracking.VelocityBias)
        self._at_m = arc_lengths_m(self.path)
        self.length_m = float(self._at_m[-1])
        self._integral = np.zeros(2)

    def reference(self, elapsed_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The reference point (world ENU m) and its velocity (m/s) ``elapsed_s`` into the retreat."""
        along_m = min(RETREAT_SPEED_M_S * max(elapsed_s, 0.0), self.length_m)
        point = path_point(self.path, self._at_m, along_m)
        if along_m >= self.length_m or self.length_m <= 0.0:
            return point, np.zeros(3)
        ahead = path_point(self.path, self._at_m, min(along_m + 0.05, self.length_m)) - point
        norm = float(np.linalg.norm(ahead[:2]))
        velocity = np.zeros(3) if norm <= 1e-9 else np.array([*(ahead[:2] / norm * RETREAT_SPEED_M_S), 0.0])
        return point, velocity

    def velocity_enu(self, pos_enu_m: np.ndarray, elapsed_s: float, dt_s: float) -> np.ndarray:
        """The velocity to command now (world ENU m/s)."""
        point, feed = self.reference(elapsed_s)
        pos_xy = np.asarray(pos_enu_m, dtype=np.float64)[:2]
        error = point[:2] - pos_xy
        to_end_m = float(np.linalg.norm(self.path[-1, :2] - pos_xy))
        speed_limit = min(RETREAT_MAX_SPEED_M_S, math.sqrt(2.0 * RETREAT_APPROACH_DECEL_M_S2 * to_end_m))
        horizontal = feed[:2] + RETREAT_POSITION_GAIN_PER_S * error
        speed = float(np.linalg.norm(horizontal))
        if speed > speed_limit:
            horizontal *= speed_limit / speed
        if self.integral:
            self._integral += error * dt_s
            limit = RETREAT_INTEGRAL_MAX_M_S / RETREAT_INTEGRAL_GAIN_PER_S2
            norm = float(np.linalg.norm(self._integral))
            if norm > limit:
                self._integral *= limit / norm
            horizontal = horizontal + RETREAT_INTEGRAL_GAIN_PER_S2 * self._integral
            speed = float(np.linalg.norm(horizontal))
            if speed > RETREAT_MAX_SPEED_M_S:
                horizontal *= RETREAT_MAX_SPEED_M_S / speed
        climb = float(np.clip(RETREAT_CLIMB_GAIN_PER_S * (point[2] - pos_enu_m[2]), -RETREAT_CLIMB_MAX_M_S, RETREAT_CLIMB_MAX_M_S))
        return np.array([horizontal[0], horizontal[1], climb])

    def arrived(self, pos_enu_m: np.ndarray, elapsed_s: float) -> bool:
        """The reference is at the path's end and the vehicle within ``RETREAT_ARRIVED_M`` of it."""
        if RETREAT_SPEED_M_S * elapsed_s < self.length_m:
            return False
        return float(np.linalg.norm(self.path[-1, :2] - np.asarray(pos_enu_m)[:2])) < RETREAT_ARRIVED_M


def arc_lengths_m(path: np.ndarray) -> np.ndarray:
    """[N] horizontal length along the polyline ``path`` [N, 3] to each of its points (m)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1))])


def path_point(path: np.ndarray, at_m: np.ndarray, along_m: float) -> np.ndarray:
    """The point ``along_m`` metres (horizontal length) along the polyline ``path``."""
    if len(path) == 1 or along_m <= 0.0:
        return path[0]
    k = min(int(np.searchsorted(at_m, along_m)), len(path) - 1)
    span = at_m[k] - at_m[k - 1]
    share = 1.0 if span <= 0.0 else (along_m - at_m[k - 1]) / span
    return path[k - 1] + min(share, 1.0) * (path[k] - path[k - 1])


# The dry run's landing site (:func:`choose_landing_site`): a point of its way back -- from where
# the vehicle stopped to the path flown's end, then back along the path -- nearest to
# mission.land_retreat_m back along the path, whose column down to the floor is clear of what the
# episode's depth frames showed (runtime.camera.surfaces) by at least mission.land_clearance_m (the
# vehicle's radius plus the landing's drift), reached by a way that keeps
# mission.land_way_clearance_m from the surfaces seen at the height it flies (two retreats at
# level 15 touched a thin post or a slab's edge beside the path).  Landing nearer the stop instead
# (the nearest clear point, 0.1 m median travel) put 4 of 35 PX4 SIH landings into the wall behind
# the goal: the landing's drift reached the 0.8 m then asked.  A camera that showed nothing leaves
# nothing to choose by: mission.land_retreat_m back, unchecked.
# When no point of the way back is clear and reached, a straight step away from where it stopped
# (LANDING_AWAY_DIRECTIONS headings, up to LANDING_AWAY_MAX_M) is: with the stereo camera on PX4
# SIH, 2 of 40 flights stopped 0.03-0.1 m from the wall behind the goal with the way back passing
# an obstacle nearer than mission.land_way_clearance_m, landed where they stopped and drifted into
# the wall on the way down.
LANDING_SITE_STEP_M = 0.1  # the candidates' spacing along the way
LANDING_HEIGHT_MARGIN_M = 0.3  # surfaces seen up to this far above the landing height are in its way
LANDING_WAY_HEIGHT_MARGIN_M = 0.3  # surfaces seen within the flight height +- this are in the way there
LANDING_AWAY_DIRECTIONS = 16  # headings of the straight steps away from the stop
LANDING_AWAY_MAX_M = 1.5  # their longest (m): a step beside the path is blind where the camera did not look


# The dry run's approach to its last goal: the brake that follows the goal carries the vehicle on
# along its velocity (PX4 SIH: 1.22 s from the policy's speeds to below 0.2 m/s), and at levels 10
# and 15 it carried it into the wall 0.5-1 m behind the goal (level 10 seed 7002; level 15 seed 7010
# in two campaigns).
# Within APPROACH_GOAL_M of that goal the command's horizontal speed is capped to what the brake
# stops in the free distance the surfaces seen leave ahead along the command
# (runtime.camera.surfaces; a corridor APPROACH_HALF_WIDTH_M either side, at the flight height),
# less APPROACH_MARGIN_M: v x APPROACH_DELAY_S + v^2 / (2 x APPROACH_DECEL_M_S2) <= free - margin.
APPROACH_GOAL_M = 3.0  # from the goal (m, the estimate's): where the cap applies
APPROACH_HALF_WIDTH_M = 0.3  # the vehicle's radius (0.2 m) and a cell
APPROACH_MARGIN_M = 0.5  # the vehicle's radius and the estimate's error against what was seen
APPROACH_DELAY_S = 0.3  # PX4's 0.18 s, a control period and the camera's latency
APPROACH_DECEL_M_S2 = 1.2  # PX4 SIH's brake, on average from the policy's speeds
APPROACH_MIN_M_S = 0.3  # a surface seen where there is none slows the vehicle, never holds it
APPROACH_LOOKAHEAD_M = 4.0  # the free distance looked at (at 2 m/s the stop takes 2.3 m)


def approach_speed_cap_m_s(free_ahead_m: float) -> float:
    """The fastest horizontal speed (m/s) from which the brake stops within ``free_ahead_m`` less
    ``APPROACH_MARGIN_M`` (:data:`APPROACH_DELAY_S`, :data:`APPROACH_DECEL_M_S2`), at least
    ``APPROACH_MIN_M_S``."""
    room_m = max(free_ahead_m - APPROACH_MARGIN_M, 0.0)
    delay, decel = APPROACH_DELAY_S, APPROACH_DECEL_M_S2
    return max(decel * (math.sqrt(delay**2 + 2.0 * room_m / decel) - delay), APPROACH_MIN_M_S)


def cap_approach(cmd_flu: np.ndarray, pos_enu_m: np.ndarray, yaw_enu_rad: float, goal_enu_m: np.ndarray,
                 seen: SeenSurfaces) -> tuple[np.ndarray, float | None]:  # fmt: skip
    """The velocity command ``cmd_flu`` (forward, left, up m/s, yaw rate rad/s) with its horizontal
    speed capped by :func:`approach_speed_cap_m_s` along its own heading, from ``pos_enu_m`` (local
    ENU) within ``APPROACH_GOAL_M`` of ``goal_enu_m``; and the cap (m/s) where it applied (lowered
    the speed), else None."""
    pos = np.asarray(pos_enu_m, dtype=np.float64)
    speed_m_s = float(np.hypot(cmd_flu[0], cmd_flu[1]))
    if float(np.linalg.norm(np.asarray(goal_enu_m, dtype=np.float64)[:2] - pos[:2])) > APPROACH_GOAL_M or speed_m_s == 0.0:
        return cmd_flu, None
    heading = yaw_enu_rad + math.atan2(cmd_flu[1], cmd_flu[0])
    z = float(pos[2])
    free_m = seen.free_ahead_m(pos[:2], heading, APPROACH_HALF_WIDTH_M, z + LANDING_WAY_HEIGHT_MARGIN_M,
                               z - LANDING_WAY_HEIGHT_MARGIN_M, APPROACH_LOOKAHEAD_M)  # fmt: skip
    cap = approach_speed_cap_m_s(free_m)
    if speed_m_s <= cap:
        return cmd_flu, None
    capped = np.array(cmd_flu, dtype=np.float64)
    capped[:2] *= cap / speed_m_s
    return capped, cap


def landing_way(flown_enu_m: np.ndarray, stop_enu_m: np.ndarray, back_m: float) -> np.ndarray:
    """The way back to a landing site (local ENU m, (N, 3), at the height where the vehicle
    stopped): from ``stop_enu_m`` to the end of the path flown (``flown_enu_m``, positions in
    order), then back along it for ``back_m`` of horizontal length (:func:`retreat_path`)."""
    stop = np.asarray(stop_enu_m, dtype=np.float64).reshape(1, 3)
    flown = np.asarray(flown_enu_m, dtype=np.float64).reshape(-1, 3)
    way = stop if len(flown) == 0 else np.vstack([stop, retreat_path(flown, back_m)])
    # At the height it stopped at, not the path's: on PX4 the estimate's height drifts from the
    # truth, and a path that came down to the goal led back up into the ceiling (2 of 6 flights).
    way[:, 2] = stop[0, 2]
    return way


def blind_travel_m(way_enu_m: np.ndarray, back_m: float) -> float:
    """How far along ``way_enu_m`` (:func:`landing_way`) lies the point ``back_m`` back along the
    path flown (0: where the vehicle stopped): a site chosen by nothing seen."""
    at_m = arc_lengths_m(np.asarray(way_enu_m, dtype=np.float64).reshape(-1, 3))
    if back_m <= 0.0 or len(at_m) < 2:
        return 0.0
    return round(float(min(at_m[1] + back_m, at_m[-1])), 3)


@dataclass(frozen=True)
class LandingSite:
    """Where to land: ``travel_m`` of horizontal length along the way back (:func:`landing_way`;
    0: where the vehicle stopped) or, with ``away_heading_enu_rad``, along a straight step away
    from where it stopped at that heading (local ENU, from +x toward +y); its clearance to the
    surfaces seen below it (m; None: none seen) and the least clearance on the way there at the
    flight height (m; None: none seen), whether both meet what was asked, how many cells of the
    grid held a surface; ``path_enu_m`` is the way there (N, 3), where it stopped first."""

    travel_m: float
    clearance_m: float | None
    way_clearance_m: float | None
    clear: bool
    surface_cells: int
    away_heading_enu_rad: float | None = None
    path_enu_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((1, 3)), repr=False, compare=False)

    def record(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k != "path_enu_m"}


@dataclass(frozen=True)
class _Candidates:
    """The points every ``LANDING_SITE_STEP_M`` along one way: their travel (m), their clearance
    below (m), the least clearance on the way to each at the flight height (m), and whether each is
    reached (:func:`choose_landing_site`)."""

    way: np.ndarray
    travels_m: np.ndarray
    below_m: np.ndarray
    way_least_m: np.ndarray
    reached: np.ndarray


def _candidates(way: np.ndarray, seen: SeenSurfaces, near_cells: np.ndarray, other_cells: np.ndarray, stop_near_m: float,
                way_clearance_m: float) -> _Candidates:  # fmt: skip
    at_m = arc_lengths_m(way)
    travels_m = np.arange(0.0, at_m[-1] + 1e-9, LANDING_SITE_STEP_M)
    points = np.array([path_point(way, at_m, t)[:2] for t in travels_m])
    below = seen.clearance_m(points, float(way[0, 2]) + LANDING_HEIGHT_MARGIN_M)
    from_near, from_others = nearest_m(points, near_cells), nearest_m(points, other_cells)
    way_least = np.minimum.accumulate(np.minimum(from_near, from_others))
    # a point is reached if no point before it on the way (itself included) came nearer than that
    reached = np.logical_and.accumulate((from_others >= way_clearance_m) & (from_near >= stop_near_m - LANDING_SITE_STEP_M))
    return _Candidates(way, travels_m, below, way_least, reached)


def _site(c: _Candidates, k: int, ok: bool, cells: int, heading_rad: float | None) -> LandingSite:
    travel_m = round(float(c.travels_m[k]), 3)
    return LandingSite(
        travel_m=travel_m,
        clearance_m=round(float(c.below_m[k]), 3) if np.isfinite(c.below_m[k]) else None,
        way_clearance_m=round(float(c.way_least_m[k]), 3) if np.isfinite(c.way_least_m[k]) else None,
        clear=ok,
        surface_cells=cells,
        away_heading_enu_rad=None if heading_rad is None else round(heading_rad, 3),
        path_enu_m=cut_path(c.way, travel_m),
    )


def choose_landing_site(way_enu_m: np.ndarray, seen: SeenSurfaces, preferred_back_m: float, clearance_m: float,
                        way_clearance_m: float) -> LandingSite:  # fmt: skip
    """The landing site on ``way_enu_m`` (from :func:`landing_way`, its first point where the
    vehicle stopped): of the points every ``LANDING_SITE_STEP_M`` along it, the one nearest to
    ``preferred_back_m`` back along the path flown whose clearance to the surfaces seen below it is
    at least ``clearance_m`` and whose way there keeps at least ``way_clearance_m`` from the surfaces
    seen at the flight height (from those already nearer where it stopped: no nearer than there,
    to a candidate's spacing).  Else the nearest such point on a straight step away from where it
    stopped (``LANDING_AWAY_DIRECTIONS`` headings, ``LANDING_AWAY_MAX_M`` at most); else, of the
    points reached so on either, the clearest.  ``seen`` holding no surface: ``preferred_back_m``
    back, unchecked."""
    way = np.asarray(way_enu_m, dtype=np.float64).reshape(-1, 3)
    height_z_m = float(way[0, 2])
    preferred_m = blind_travel_m(way, preferred_back_m)
    if len(seen) == 0:
        return LandingSite(preferred_m, None, None, True, 0, path_enu_m=cut_path(way, preferred_m))
    # The surfaces at the flight height: those nearer than way_clearance_m where the vehicle stopped
    # it moves away from (no nearer to them than it was); all others at way_clearance_m at least.
    beside_cells = seen.cells_xy_m(height_z_m + LANDING_WAY_HEIGHT_MARGIN_M, height_z_m - LANDING_WAY_HEIGHT_MARGIN_M)
    near = nearest_m(beside_cells, way[:1, :2]) < way_clearance_m
    near_cells, other_cells = beside_cells[near], beside_cells[~near]
    stop_near_m = float(nearest_m(way[:1, :2], near_cells)[0])
    back = _candidates(way, seen, near_cells, other_cells, stop_near_m, way_clearance_m)
    ok = back.reached & (back.below_m >= clearance_m)
    if ok.any():
        order = np.argsort(np.abs(back.travels_m - preferred_m), kind="stable")
        return _site(back, order[int(np.argmax(ok[order]))], True, len(seen), None)
    # (candidates, heading): the way back first (no heading), then the straight steps away
    ways = [(back, None)] + [
        (_candidates(np.vstack([way[0], way[0] + [LANDING_AWAY_MAX_M * math.cos(h), LANDING_AWAY_MAX_M * math.sin(h), 0.0]]),
                     seen, near_cells, other_cells, stop_near_m, way_clearance_m), float(h))
        for h in np.arange(LANDING_AWAY_DIRECTIONS) * (2.0 * math.pi / LANDING_AWAY_DIRECTIONS)
    ]  # fmt: skip
    # the shortest clear step (of equal ones the clearest below); else the clearest point reached on any way
    steps = [(c.travels_m[k], -c.below_m[k], i, k) for i, (c, _) in enumerate(ways) if i > 0
             for k in np.flatnonzero(c.reached & (c.below_m >= clearance_m))]  # fmt: skip
    clear = bool(steps)
    _, _, i, k = min(steps or [(-c.below_m[k], c.travels_m[k], i, k) for i, (c, _) in enumerate(ways) for k in np.flatnonzero(c.reached)])
    return _site(ways[i][0], k, clear, len(seen), ways[i][1])


def measured_speed_m_s(vehicle: VehicleState) -> float:
    """|velocity| (m/s, world ENU) as telemetry last reported it; NaN before any."""
    return float(np.linalg.norm(vehicle.vel_enu_m_s))


def brake_record(ended: str, t_brake_ns: int, now_ns: int, vehicle: VehicleState) -> dict:
    """The summary's record of one brake: how it ended, how long it took (s), the speed at Hold (m/s)."""
    speed = measured_speed_m_s(vehicle)
    return {"ended": ended, "duration_s": round((now_ns - t_brake_ns) / _NS_PER_S, 3),
            "speed_at_hold_m_s": round(speed, 3) if math.isfinite(speed) else None}  # fmt: skip


class Watchdog:
    """Detects faults and drives the safe-state response through the :class:`CommandGate`."""

    def __init__(
        self,
        config: WatchdogConfig,
        gate: CommandGate,
        on_event: Callable[[dict], None] | None = None,
    ) -> None:
        self.config = config
        self.gate = gate
        self._on_event = on_event
        self.trips: list[Trip] = []
        self._t0_ns = 0
        self._supervising = False
        self._offboard_seen = False
        self._start_xy_enu_m = np.zeros(2)
        self._home_z_enu_m = 0.0
        self._depth_invalid = OverBound()
        self._hold_pending = False
        self._t_brake_sent_ns = 0
        self.brake: dict | None = None  # how the trip response's brake ended (brake_record)
        self._tracking = TrackingMonitor(config.tracking_error_max_m_s, config.tracking_lag_s, config.tracking_window_s)
        self._tracking_status: TrackingStatus | None = None
        self._t_posvel_seen_ns = 0
        self._t_att_seen_ns = 0
        self._t_telemetry_seen_ns = 0
        self._link_gap_ns = 0  # the longest gap in telemetry since supervision started
        self._link_stale_seen = False
        self._tilt_over = OverBound()
        self._tilt_rad = 0.0
        self._status_seq_seen = 0
        self._armed_seen = False

    # ------------------------------------------------------------------ state

    @property
    def tripped(self) -> Trip | None:
        """The trip that set the response, or None."""
        return next((t for t in self.trips if t.response != Response.ALREADY_TRIPPED), None)

    @property
    def pilot_took_over(self) -> bool:
        return any(t.cause == TripCause.PILOT_LEFT_OFFBOARD for t in self.trips)

    @property
    def supervising(self) -> bool:
        return self._supervising

    @property
    def start_xy_enu_m(self) -> np.ndarray:
        """Where supervision started (local ENU x, y, m): the centre of the horizontal geofence."""
        return self._start_xy_enu_m.copy()

    @property
    def tracking_sustained_peak_m_s(self) -> float:
        """This episode's largest tracking error that held for a whole ``tracking_window_s`` (m/s):
        a trip needs it above ``tracking_error_max_m_s``; in normal flight it shows the margin."""
        return self._tracking.sustained_peak_m_s

    def records(self) -> list[dict]:
        return [t.record(self._t0_ns) for t in self.trips]

    def set_geofence_radius(self, radius_m: float) -> None:
        """Change the horizontal geofence radius (m) from now on (validated as the config is)."""
        self.config = dataclasses.replace(self.config, geofence_radius_m=radius_m)

    def start(self, now_ns: int, state: VehicleState) -> None:
        """Begin supervising: offboard was entered at ``state``'s position (local ENU, m)."""
        if state.home_enu_m is None or not np.all(np.isfinite(state.pos_enu_m)):
            raise ValueError("watchdog needs a position and a home position to start: wait for Vehicle.wait_ready()")
        self._t0_ns = now_ns
        self._supervising = True
        self._offboard_seen = state.flight_mode == MODE_OFFBOARD
        self._start_xy_enu_m = np.asarray(state.pos_enu_m[:2], dtype=np.float64).copy()
        self._home_z_enu_m = float(state.home_enu_m[2])
        self._depth_invalid.reset()
        self._hold_pending = False
        self.brake = None
        cfg = self.config
        self._tracking = TrackingMonitor(cfg.tracking_error_max_m_s, cfg.tracking_lag_s, cfg.tracking_window_s)
        self._tracking.start(now_ns, state.vel_enu_m_s, state.yaw_enu_rad)
        self._tracking_status = None
        self._t_posvel_seen_ns = state.t_posvel_ns
        self._t_att_seen_ns = 0
        self._t_telemetry_seen_ns = state.t_telemetry_ns
        self._link_gap_ns = 0
        self._link_stale_seen = False
        self._tilt_over.reset()
        # Only what the autopilot says from now on counts; it must be armed once to be disarmed.
        self._status_seq_seen = state.status_texts[-1].seq if state.status_texts else 0
        self._armed_seen = state.armed
        self.trips.clear()
        self.gate.open_for_policy()

    async def check_goal(self, goal_enu_m: np.ndarray, now_ns: int) -> Trip | None:
        """Right after :meth:`start`: trip (geofence) if the goal (local ENU, m) is outside the fence."""
        dist_m = float(np.linalg.norm(np.asarray(goal_enu_m[:2], dtype=np.float64) - self._start_xy_enu_m))
        height_m = float(goal_enu_m[2]) - self._home_z_enu_m
        cfg = self.config
        if dist_m > cfg.geofence_radius_m:
            detail = f"goal {dist_m:.1f} m from start > geofence radius {cfg.geofence_radius_m:.1f} m: refused"
        elif not cfg.altitude_min_m <= height_m <= cfg.altitude_max_m:
            detail = (f"goal height {height_m:.2f} m above home outside [{cfg.altitude_min_m:.2f}, "
                      f"{cfg.altitude_max_m:.2f}] m: refused")  # fmt: skip
        else:
            return None
        return await self.trip(TripCause.GEOFENCE, detail, now_ns, now_ns)

    def refuse_start(self, cause: TripCause, detail: str, t_request_ns: int, now_ns: int) -> Trip:
        """Record a start that did not happen (e.g. the autopilot refused offboard) as a trip
        with response Hold; times count from ``t_request_ns``.  The caller commands Hold."""
        self._t0_ns = t_request_ns
        self._supervising = False
        self.trips.clear()
        trip = Trip(cause, detail, now_ns, max(0.0, (now_ns - t_request_ns) / _NS_PER_MS), Response.HOLD)
        self.trips.append(trip)
        log.error("watchdog trip %s: %s (detected in %.1f ms) -> %s", cause.value, detail, trip.detect_ms, trip.response.value)
        self._emit("trip", trip)
        return trip

    def stop(self) -> None:
        """Stop supervising (the loop ended and commands Hold itself): mode changes are ours now."""
        self._supervising = False

    # ------------------------------------------------------------------ per-step checks

    def note_command(self, t_ns: int, cmd_flu: np.ndarray) -> None:
        """A velocity command was sent at ``t_ns``: (vx, vy, vz[, wz]) body FLU m/s as the contract
        maps the action, which PX4 flies in the vehicle frame V (yaw only): the tracking reference."""
        self._tracking.command(t_ns, np.asarray(cmd_flu, dtype=np.float64)[:3])

    def note_depth(self, t_capture_ns: int, invalid_frac: float) -> None:
        """Record each frame's raw invalid-depth fraction for the too-long-invalid check."""
        self._depth_invalid.update(t_capture_ns, invalid_frac > self.config.depth_invalid_frac_max)

    def _note_link_gap(self, v: VehicleState, now_ns: int) -> None:
        """Keep the longest telemetry gap of the episode; a gap counts once a check saw the
        telemetry stale (older than ``telemetry_stale_ms``) before it resumed."""
        if v.t_telemetry_ns > self._t_telemetry_seen_ns:
            if self._link_stale_seen:
                self._link_gap_ns = max(self._link_gap_ns, v.t_telemetry_ns - self._t_telemetry_seen_ns)
            self._link_stale_seen = False
            self._t_telemetry_seen_ns = v.t_telemetry_ns
        elif self._t_telemetry_seen_ns and now_ns - self._t_telemetry_seen_ns > self.config.telemetry_stale_ms * _NS_PER_MS:
            self._link_stale_seen = True

    async def check_telemetry(self, v: VehicleState, now_ns: int) -> Trip | None:
        """Trip (stale_telemetry) when the position/attitude is older than ``telemetry_stale_ms``.
        Run by every tick and by the policy task before it computes a step, so no command is ever
        computed from state the periodic check would already call stale."""
        if not self._supervising or self.tripped is not None:
            return None
        limit_ns = int(self.config.telemetry_stale_ms * _NS_PER_MS)
        t_ref = max(v.t_telemetry_ns, self._t0_ns)
        if now_ns - t_ref <= limit_ns:
            return None
        return await self.trip(
            TripCause.STALE_TELEMETRY,
            f"position/attitude {(now_ns - v.t_telemetry_ns) / _NS_PER_MS:.0f} ms old > {self.config.telemetry_stale_ms:.0f} ms",
            t_ref + limit_ns, now_ns,
        )  # fmt: skip

    async def check_action(self, action: np.ndarray, t_step_started_ns: int, now_ns: int) -> Trip | None:
        """Before a command is sent: trip on a NaN/Inf action or a step past its trip limit."""
        if not self._supervising:
            return None
        if not np.all(np.isfinite(action)):
            return await self.trip(TripCause.BAD_ACTION, f"policy action {np.asarray(action).tolist()}", now_ns, now_ns)
        limit_ns = int(self.config.step_trip_ms * _NS_PER_MS)
        if now_ns - t_step_started_ns > limit_ns:
            return await self.trip(
                TripCause.STEP_DEADLINE,
                f"step took {(now_ns - t_step_started_ns) / _NS_PER_MS:.1f} ms > {self.config.step_trip_ms:.1f} ms",
                t_step_started_ns + limit_ns,
                now_ns,
            )
        return None

    # ------------------------------------------------------------------ periodic checks

    async def tick(self, inputs: WatchInputs) -> Trip | None:
        """Run the time-based checks and the pending Hold; returns a new trip, if any."""
        if not self._supervising:
            return None
        now = inputs.now_ns
        cfg = self.config
        v = inputs.vehicle
        if v.flight_mode == MODE_OFFBOARD and v.t_mode_ns >= self._t0_ns:
            self._offboard_seen = True
        trip: Trip | None = None
        self._note_link_gap(v, now)
        if self._offboard_seen and v.flight_mode != MODE_OFFBOARD and not self.gate.released and not self._hold_sent():
            if self._link_gap_ns >= cfg.offboard_loss_s * _NS_PER_S:
                trip = await self.trip(TripCause.OFFBOARD_LOSS_FAILSAFE,
                                       f"flight mode is now {v.flight_mode} after the link was down "
                                       f"{self._link_gap_ns / _NS_PER_S:.1f} s >= offboard_loss_s {cfg.offboard_loss_s:g} s",
                                       v.t_mode_ns, now)  # fmt: skip
            else:
                trip = await self.trip(TripCause.PILOT_LEFT_OFFBOARD, f"flight mode is now {v.flight_mode}", v.t_mode_ns, now)
        if self.tripped is None:
            trip = await self._check_faults(inputs) or trip
        if self._hold_pending and not self.gate.released:
            tripped = self.tripped
            assert tripped is not None
            ended = brake_ended(v, tripped.t_ns, now, cfg)
            if ended is not None:
                await self._send_hold(tripped, now, brake_record(ended, tripped.t_ns, now, v))
            elif now - self._t_brake_sent_ns >= CONTROL_PERIOD_S * _NS_PER_S:
                await self._send_brake(v, now)
        return trip

    async def _check_faults(self, inputs: WatchInputs) -> Trip | None:
        cfg, now, v = self.config, inputs.now_ns, inputs.vehicle
        trip = await self._check_vehicle_fault(v, now)
        if trip is not None:
            return trip
        frame_limit = int(cfg.frame_stale_ms * _NS_PER_MS)
        t_frame_ref = max(inputs.t_last_frame_capture_ns, self._t0_ns)
        if now - t_frame_ref > frame_limit:
            age_ms = (now - inputs.t_last_frame_capture_ns) / _NS_PER_MS if inputs.t_last_frame_capture_ns else math.inf
            if inputs.frames_rejected:
                cause, detail = TripCause.BAD_FRAMES, (
                    f"no valid frame for {age_ms:.0f} ms > {cfg.frame_stale_ms:.0f} ms: {inputs.frames_rejected} "
                    f"frames rejected since, the last because {inputs.last_rejection}"
                )
            else:
                cause, detail = TripCause.STALE_FRAME, f"newest frame {age_ms:.0f} ms old > {cfg.frame_stale_ms:.0f} ms"
            return await self.trip(cause, detail, t_frame_ref + frame_limit, now)
        step_limit = int(cfg.step_trip_ms * _NS_PER_MS)
        if inputs.t_step_started_ns and now - inputs.t_step_started_ns > step_limit:
            return await self.trip(
                TripCause.STEP_DEADLINE,
                f"step running for {(now - inputs.t_step_started_ns) / _NS_PER_MS:.0f} ms > {cfg.step_trip_ms:.0f} ms",
                inputs.t_step_started_ns + step_limit, now,
            )  # fmt: skip
        if trip := await self.check_telemetry(v, now):
            return trip
        if trip := await self._trip_if_held(self._depth_invalid, cfg.depth_invalid_max_s, TripCause.DEPTH_INVALID,
                                            lambda: f"depth invalid fraction > {cfg.depth_invalid_frac_max:.2f}", "", now):  # fmt: skip
            return trip
        if v.t_posvel_ns:
            dist_m = float(np.linalg.norm(np.asarray(v.pos_enu_m[:2]) - self._start_xy_enu_m))
            height_m = float(v.pos_enu_m[2]) - self._home_z_enu_m
            if dist_m > cfg.geofence_radius_m:
                return await self.trip(
                    TripCause.GEOFENCE, f"{dist_m:.1f} m from start > {cfg.geofence_radius_m:.1f} m", v.t_posvel_ns, now
                )
            if not cfg.altitude_min_m <= height_m <= cfg.altitude_max_m:
                return await self.trip(
                    TripCause.GEOFENCE,
                    f"height {height_m:.2f} m above home outside [{cfg.altitude_min_m:.2f}, {cfg.altitude_max_m:.2f}] m",
                    v.t_posvel_ns, now,
                )  # fmt: skip
        return await self._check_outcome(v, now)

    async def _check_vehicle_fault(self, v: VehicleState, now: int) -> Trip | None:
        """The autopilot's own word: a STATUSTEXT of severity CRITICAL or worse, or a disarm."""
        new = [t for t in v.status_texts if t.seq > self._status_seq_seen]
        if new:
            self._status_seq_seen = new[-1].seq
        fault = next((t for t in new if t.is_fault), None)
        if fault is not None:
            return await self.trip(TripCause.VEHICLE_FAULT, f"autopilot {fault.severity}: {fault.text}", fault.t_ns, now)
        if v.armed:
            self._armed_seen = True
        elif self._armed_seen:
            self._armed_seen = False
            return await self.trip(TripCause.VEHICLE_FAULT, "the autopilot disarmed in flight", v.t_armed_ns or now, now)
        return None

    async def _check_outcome(self, v: VehicleState, now: int) -> Trip | None:
        """Tracking (the measured velocity follows the commands) and attitude (not flipped)."""
        cfg = self.config
        if v.t_posvel_ns > self._t_posvel_seen_ns:
            self._t_posvel_seen_ns = v.t_posvel_ns
            self._tracking_status = self._tracking.update(v.t_posvel_ns, v.vel_enu_m_s, v.yaw_enu_rad)

        def tracking_error() -> str:
            status = self._tracking_status
            fwd, left, up = (round(float(e), 2) for e in status.error_vehicle_m_s)
            return (f"velocity error {status.error_m_s:.2f} m/s (vehicle frame forward/left/up {fwd}/{left}/{up}) "
                    f"> {cfg.tracking_error_max_m_s:.2f} m/s")  # fmt: skip

        if trip := await self._trip_if_held(self._tracking.over, cfg.tracking_window_s, TripCause.TRACKING, tracking_error,
                                            ": the vehicle does not follow its commands", now):  # fmt: skip
            return trip
        if v.t_att_ns > self._t_att_seen_ns:
            self._t_att_seen_ns = v.t_att_ns
            self._tilt_rad = tilt_rad(v.quat_enu_flu)
            self._tilt_over.update(v.t_att_ns, math.degrees(self._tilt_rad) > cfg.tilt_max_deg)
        return await self._trip_if_held(self._tilt_over, cfg.tilt_window_s, TripCause.ATTITUDE,
                                        lambda: f"tilt {math.degrees(self._tilt_rad):.0f} deg > {cfg.tilt_max_deg:.0f} deg",
                                        ": flipped or tumbling", now)  # fmt: skip

    async def _trip_if_held(self, over: OverBound, window_s: float, cause: TripCause, what: Callable[[], str],
                            why: str, now: int) -> Trip | None:  # fmt: skip
        """Trip with ``cause`` once ``over`` has held for longer than ``window_s``, the fault dated
        to when the window ran out: "<what()> for X s > <window> s<why>" (``what`` is only formatted
        for a trip, not on every check)."""
        window_ns = int(window_s * _NS_PER_S)
        if not over.held_past(window_ns, now):
            return None
        since = over.since_ns
        return await self.trip(cause, f"{what()} for {(now - since) / _NS_PER_S:.2f} s > {window_s:.2f} s{why}",
                               since + window_ns, now)  # fmt: skip

    # ------------------------------------------------------------------ response

    async def trip(self, cause: TripCause, detail: str, t_fault_ns: int, now_ns: int) -> Trip:
        """Record a trip and respond: hover now (Hold after the grace), or stop commanding."""
        if cause == TripCause.PILOT_LEFT_OFFBOARD:
            response = Response.STOP_COMMANDING
        elif cause == TripCause.OFFBOARD_LOSS_FAILSAFE:
            response = Response.VEHICLE_FAILSAFE
        elif self.tripped is None:
            response = Response.HOVER_THEN_HOLD
        else:
            response = Response.ALREADY_TRIPPED
        trip = Trip(cause, detail, now_ns, max(0.0, (now_ns - t_fault_ns) / _NS_PER_MS), response)
        self.trips.append(trip)
        log.error("watchdog trip %s: %s (detected in %.1f ms) -> %s", cause.value, detail, trip.detect_ms, response.value)
        if response in (Response.STOP_COMMANDING, Response.VEHICLE_FAILSAFE):
            self.gate.release()
            self._hold_pending = False
        elif response == Response.HOVER_THEN_HOLD:
            self._hold_pending = True
            self._t_brake_sent_ns = now_ns
            try:
                await self.gate.hover()
            except VehicleError as err:
                log.error("watchdog: hover setpoint failed (%s); Hold follows after the grace period", err)
        self._emit("trip", trip)
        return trip

    async def _send_brake(self, v: VehicleState, now_ns: int) -> None:
        """The brake's next setpoint (at the control rate while Hold waits); a failed send is
        logged, MAVSDK keeps re-sending the last one."""
        self._t_brake_sent_ns = now_ns
        try:
            await self.gate.send_own(brake_setpoint(v, now_ns, self.config))
        except VehicleError as err:
            log.error("watchdog: brake setpoint failed (%s); Hold follows when braked or at brake_timeout_s", err)

    async def _send_hold(self, trip: Trip, now_ns: int, brake: dict) -> None:
        try:
            sent = await self.gate.hold()
        except VehicleError as err:
            log.error("watchdog: Hold (offboard.stop) failed (%s); retrying on the next check", err)
            return
        self._hold_pending = False
        self.brake = brake
        if sent:
            trip.hold_t_ns = now_ns
            log.warning("watchdog: vehicle commanded to Hold %.2f s after the %s trip (brake: %s)",
                        (now_ns - trip.t_ns) / _NS_PER_S, trip.cause.value, brake)  # fmt: skip
            self._emit("hold", trip)

    def _hold_sent(self) -> bool:
        trip = self.tripped
        return trip is not None and trip.hold_t_ns is not None

    def _emit(self, event: str, trip: Trip) -> None:
        if self._on_event is not None:
            self._on_event({"event": event, **trip.record(self._t0_ns)})
