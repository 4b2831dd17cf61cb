"""Every number that training, sim and runtime must agree on (DESIGN §2).

Change a value here and bump ``CONTRACT_VERSION``: models carry the version and the values in
their ONNX metadata, and the runtime refuses a model whose contract differs.
"""

from __future__ import annotations

import math

CONTRACT_VERSION = "1"

# Timing: the policy runs at the camera rate in training and flight alike.
CAMERA_RATE_HZ = 15.0
CONTROL_PERIOD_S = 1.0 / CAMERA_RATE_HZ
EPISODE_DURATION_S = 10.0

# Camera: Intel RealSense D455 as mounted, depth aligned to color (pinhole, square pixels).
CAMERA_WIDTH_PX = 848
CAMERA_HEIGHT_PX = 480
CAMERA_HFOV_RAD = math.radians(87.0)
# Reduced raw size the sim renders at (same aspect as the D455 within 0.1%).
SIM_CAMERA_WIDTH_PX = 212
SIM_CAMERA_HEIGHT_PX = 120

# Image preprocessing (runtime.contract.images).
IMAGE_SIZE_PX = 224
DEPTH_MAX_M = 10.0  # normalisation range: d / DEPTH_MAX_M clipped to [0, 1]
DEPTH_INVALID_VALUE = 0.0  # invalid depth after normalisation, as the sensor reports it

# Observation (runtime.contract.observation): 15 state values then the latent.
GOAL_DISTANCE_CLIP_M = 12.0
LATENT_DIM = 64
STATE_DIM = 15
OBSERVATION_DIM = STATE_DIM + LATENT_DIM
OBS_GOAL_DIR_V = slice(0, 3)
OBS_GOAL_DIST = slice(3, 4)
OBS_ROLL_PITCH = slice(4, 6)
OBS_VEL_BODY_FLU = slice(6, 9)
OBS_ANGVEL_BODY_FLU = slice(9, 12)
OBS_PREV_ACTION = slice(12, 15)
OBS_LATENT = slice(15, 79)

# Action (runtime.contract.action): a in [-1, 1]^3.
ACTION_DIM = 3
MAX_SPEED_M_S = 2.0  # speed = (a1 + 1) * MAX_SPEED_M_S / 2
MAX_INCLINATION_RAD = math.pi / 4  # incl = a2 * MAX_INCLINATION_RAD
MAX_YAW_RATE_RAD_S = math.pi / 3  # yaw_rate = a3 * MAX_YAW_RATE_RAD_S

# Task.
GOAL_REACHED_RADIUS_M = 1.0

# ONNX step signature (runtime.model): names and shapes with batch 1.
ONNX_INPUT_GRAY = "gray"  # [1, 1, 224, 224] float32 in [0, 1]
ONNX_INPUT_DEPTH = "depth"  # [1, 1, 224, 224] float32 in [0, 1], invalid = 0
ONNX_INPUT_STATE = "state"  # [1, 15] float32
ONNX_INPUT_HIDDEN = "hidden"  # [1, H] float32, GRU state; zeros at reset
ONNX_OUTPUT_ACTION = "action"  # [1, 3] float32, raw policy output (clipped by the runtime)
ONNX_OUTPUT_HIDDEN = "hidden_next"  # [1, H] float32
ONNX_OUTPUT_LATENT = "latent"  # [1, 64] float32
