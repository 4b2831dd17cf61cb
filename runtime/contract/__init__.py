"""The contract: every frame, unit, image, observation and action convention, defined once."""

from . import constants
from .action import (
    HOVER,
    ActionLimits,
    LimitError,
    VelocityBodyYawspeed,
    action_to_mavsdk,
    action_to_velocity_flu,
    clip_action,
    mavsdk_to_velocity_flu,
    velocity_flu_to_mavsdk,
)
from .constants import CONTRACT_VERSION, CONTROL_PERIOD_S
from .images import (
    ImageContractError,
    depth_invalid_mask,
    gray_from_bgr,
    invalid_depth_fraction,
    preprocess_depth,
    preprocess_gray,
)
from .metadata import ContractMismatchError, check_contract_metadata, contract_metadata, contract_values
from .observation import observation_state

__all__ = [
    "CONTRACT_VERSION",
    "CONTROL_PERIOD_S",
    "HOVER",
    "ActionLimits",
    "ContractMismatchError",
    "ImageContractError",
    "LimitError",
    "VelocityBodyYawspeed",
    "action_to_mavsdk",
    "action_to_velocity_flu",
    "check_contract_metadata",
    "clip_action",
    "constants",
    "contract_metadata",
    "contract_values",
    "depth_invalid_mask",
    "gray_from_bgr",
    "invalid_depth_fraction",
    "mavsdk_to_velocity_flu",
    "observation_state",
    "preprocess_depth",
    "preprocess_gray",
    "velocity_flu_to_mavsdk",
]
