"""The contract as ONNX metadata, and the check the runtime applies to every model it loads."""

from __future__ import annotations

import json

from . import constants as c

METADATA_KEY_VERSION = "cmnav.contract_version"
METADATA_KEY_VALUES = "cmnav.contract"


class ContractMismatchError(ValueError):
    """A model was built for a different contract than this runtime's."""


def contract_values() -> dict[str, object]:
    """Every value a model must agree on, JSON-serialisable."""
    return {
        "control_period_s": c.CONTROL_PERIOD_S,
        "image_size_px": c.IMAGE_SIZE_PX,
        "depth_max_m": c.DEPTH_MAX_M,
        "depth_invalid_value": c.DEPTH_INVALID_VALUE,
        "gray_range": [0.0, 1.0],
        "state_dim": c.STATE_DIM,
        "latent_dim": c.LATENT_DIM,
        "observation_dim": c.OBSERVATION_DIM,
        "goal_distance_clip_m": c.GOAL_DISTANCE_CLIP_M,
        "action_dim": c.ACTION_DIM,
        "max_speed_m_s": c.MAX_SPEED_M_S,
        "max_inclination_rad": c.MAX_INCLINATION_RAD,
        "max_yaw_rate_rad_s": c.MAX_YAW_RATE_RAD_S,
    }


def contract_metadata() -> dict[str, str]:
    """ONNX ``metadata_props`` entries that state this contract."""
    return {
        METADATA_KEY_VERSION: c.CONTRACT_VERSION,
        METADATA_KEY_VALUES: json.dumps(contract_values(), sort_keys=True),
    }


def check_contract_metadata(metadata: dict[str, str], source: str = "model") -> None:
    """Raise :class:`ContractMismatchError` naming every difference between ``metadata`` and ours."""
    fix = "re-export the model with this cmnav version (cmnav export) or run the cmnav it was built for"
    if METADATA_KEY_VERSION not in metadata or METADATA_KEY_VALUES not in metadata:
        raise ContractMismatchError(
            f"{source} carries no cmnav contract metadata ({METADATA_KEY_VERSION!r}, "
            f"{METADATA_KEY_VALUES!r}); it was not exported by cmnav: {fix}"
        )
    problems = []
    if metadata[METADATA_KEY_VERSION] != c.CONTRACT_VERSION:
        problems.append(
            f"contract version {metadata[METADATA_KEY_VERSION]!r} != runtime's {c.CONTRACT_VERSION!r}"
        )
    try:
        theirs = json.loads(metadata[METADATA_KEY_VALUES])
    except json.JSONDecodeError as err:
        raise ContractMismatchError(f"{source}: contract metadata is not valid JSON ({err}); {fix}") from err
    ours = contract_values()
    for key in sorted(set(ours) | set(theirs)):
        if key not in theirs:
            problems.append(f"{key}: missing in {source} (runtime: {ours[key]!r})")
        elif key not in ours:
            problems.append(f"{key}: unknown to this runtime ({source}: {theirs[key]!r})")
        elif not _equal(theirs[key], ours[key]):
            problems.append(f"{key}: {source} has {theirs[key]!r}, runtime has {ours[key]!r}")
    if problems:
        raise ContractMismatchError(f"{source} was built for a different contract: " + "; ".join(problems) + f"; {fix}")


def _equal(a: object, b: object) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return abs(float(a) - float(b)) <= 1e-9 * max(1.0, abs(float(b)))
    return a == b
