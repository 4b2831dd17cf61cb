"""The field: the env options that make the batched sim behave as the sensor and the vehicle do
in the field (issue 28; DESIGN §4 "The sensor as it is"), used together by Table II's ``field``
condition and by DAgger's ``--field`` training.

- depth: the simulated D455's stereo depth, projector on (``corruption="stereo"``);
- gray: auto-exposure, gain, motion blur and noise (``sim.sensor.gray``);
- image-to-command latency: the command a frame leads to reaches the autopilot this long after
  the frame was taken, drawn per episode in :data:`IMAGE_TO_COMMAND_LATENCY_S`;
- the autopilot: PX4 v1.16 SIH's identified response (``sim.dynamics.PX4_SIH_V1_16``), its
  command delays included, randomized per episode (``DynamicsRandomization``);
- the state estimate: EKF2-like delay, bias and noise (``sim.estimate``);
- the speed caps of a field config (``[policy.limits]`` of the runtime's TOML, read into the
  runtime's own ``ActionLimits``; default ``examples/cmnav.toml``: 1.0 m/s, 0.35 rad), applied by
  the runtime's mapping; the episode is lengthened by the same factor as the top speed is cut
  (the paper's 10 s at 2 m/s), so that the capped policy can still reach the goal.

What is measured and what assumed is stated where each number lives.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, replace
from pathlib import Path

from runtime.contract.action import ActionLimits, LimitError
from runtime.contract.constants import EPISODE_DURATION_S, MAX_SPEED_M_S
from sim.dynamics import PX4_SIH_V1_16, DynamicsRandomization
from sim.estimate import PX4_EKF2_CORRECTED
from sim.sensor.gray import GrayCameraConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

# The field's depth while training (DAgger's --field-depth) -> the batched env's corruption mode:
# the simulated D455's stereo matching, or its parametric stand-in (sim.sensor.approx).
FIELD_DEPTHS = {"stereo": "stereo", "approx": "stereo-approx"}
# The shipped field config (what `cmnav fly --config` reads on the Jetson).
FIELD_CONFIG_TOML = Path(__file__).resolve().parents[2] / "examples" / "cmnav.toml"
# Capture -> command sent, per episode: the runtime's measured frame age at p50 is 20-60 ms
# (the MCAP timing channel's ``frame_age``, SITL and bench runs), and the policy step on the
# Jetson adds up to ~20 ms (assumed: not measured on the Jetson here).
IMAGE_TO_COMMAND_LATENCY_S = (0.020, 0.080)


class FieldConfigError(ValueError):
    """The field config's limits cannot be read."""


def field_action_limits(path: str | Path = FIELD_CONFIG_TOML) -> ActionLimits:
    """The ``[policy.limits]`` of a runtime TOML config as the runtime's ActionLimits (absent keys:
    the contract's, as the runtime's loader gives them)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise FieldConfigError(f"field config {path} not found: the field condition takes its speed caps from a runtime "
                               f"config's [policy.limits]; run from the cmnav checkout or pass the config that will fly") from err  # fmt: skip
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise FieldConfigError(f"cannot read field config {path}: {err}: fix the file or pass another config") from err
    table = data.get("policy", {}).get("limits", {})
    known = {"max_speed_m_s", "max_inclination_rad"}
    if set(table) - known:
        raise FieldConfigError(f"{path}: unknown keys {sorted(set(table) - known)} in [policy.limits]: allowed {sorted(known)}")
    try:
        return ActionLimits(**{k: float(v) for k, v in table.items()})
    except LimitError as err:
        raise FieldConfigError(f"{path}: [policy.limits] {err}") from err


# The vehicles training flies: the batched sim's own, PX4's (below), or the field's (PX4's with the
# field config's speed caps: what a teacher of a field student learns to fly).
VEHICLES = ("ideal", "px4", "field")


def check_vehicle(vehicle: str) -> None:
    """ValueError unless ``vehicle`` is one of VEHICLES (a training config's ``vehicle``)."""
    if vehicle not in VEHICLES:
        raise ValueError(f"vehicle={vehicle!r} must be one of {VEHICLES}")


def px4_vehicle_env_overrides() -> dict:
    """The field's vehicle alone: image-to-command latency, PX4 v1.16's identified response and
    command delays (randomized per episode) and EKF2-like estimates as the runtime corrects them
    (:data:`sim.estimate.PX4_EKF2_CORRECTED`), at the contract's speeds and with the trained camera
    (what `cmnav sitl --autopilot` flies on PX4: rendered depth, no caps).
    Table II's ``px4`` condition and DAgger's ``--vehicle px4``."""
    return {
        "latency_range_s": IMAGE_TO_COMMAND_LATENCY_S,
        "dynamics": replace(PX4_SIH_V1_16, ground_contact=False),
        "dynamics_randomization": DynamicsRandomization(),
        "state_estimate": PX4_EKF2_CORRECTED,
    }


def field_vehicle_env_overrides(limits: ActionLimits | None = None) -> dict:
    """The field's vehicle: PX4's (:func:`px4_vehicle_env_overrides`) under the speed caps of a
    field config, the episode lengthened as the top speed is cut (see the module doc).  ``limits``:
    the caps (default: :func:`field_action_limits` of the shipped config).  A teacher trained for a
    field student flies this (``--vehicle field``): it observes clean depth and the true state."""
    limits = field_action_limits() if limits is None else limits
    if limits.max_speed_m_s <= 0.0:
        raise FieldConfigError("a field config with max_speed_m_s = 0 cannot fly to a goal: give a positive speed cap")
    return {
        **px4_vehicle_env_overrides(),
        "action_limits": limits,
        "episode_duration_s": EPISODE_DURATION_S * MAX_SPEED_M_S / min(limits.max_speed_m_s, MAX_SPEED_M_S),
    }


def vehicle_env_overrides(vehicle: str) -> dict:
    """The NavEnvConfig fields of a training run's ``vehicle`` (one of VEHICLES): none for the
    batched sim's own, :func:`px4_vehicle_env_overrides` for PX4's, :func:`field_vehicle_env_overrides`
    for the field's."""
    return {"ideal": dict, "px4": px4_vehicle_env_overrides, "field": field_vehicle_env_overrides}[vehicle]()


def field_env_overrides(limits: ActionLimits | None = None) -> dict:
    """The NavEnvConfig fields of the field (see the module doc), besides its depth
    (``corruption="stereo"``, which Table II's condition and DAgger set themselves): the gray
    camera and the field's vehicle (:func:`field_vehicle_env_overrides`)."""
    return {"gray_camera": GrayCameraConfig(), **field_vehicle_env_overrides(limits)}


def field_description(overrides: dict) -> dict:
    """The field settings as JSON (for table2.json and checkpoints' cards)."""
    return {key: asdict(value) if hasattr(value, "__dataclass_fields__") else value for key, value in overrides.items()}
