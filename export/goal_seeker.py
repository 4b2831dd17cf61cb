"""The goal-seeker: a small ONNX graph with the runtime's exact step signature that ignores the
images and steers toward the goal.  A plumbing check for the whole stack (frames, signs, units,
MAVSDK) and a pre-flight test for a new vehicle setup.  Built with ``onnx.helper``; no torch.

Control law, on the state vector of the contract (goal unit vector g in the vehicle frame V,
normalised distance d):
- yaw: turn toward the goal, a3 = clip(YAW_GAIN * g_y / |g_xy|), full rate while it is behind;
- speed: CRUISE_SPEED_M_S while facing the goal, slowing inside SLOWDOWN_RADIUS_M and when
  the goal is off to the side (speed ∝ cos of the bearing, zero when it is behind);
- inclination: the elevation of the goal, asin(g_z), as a fraction of the contract's maximum.
The GRU hidden state is passed through unchanged and the latent is all zeros.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from runtime.contract import constants as c
from runtime.contract import contract_metadata

CRUISE_SPEED_M_S = 1.0
SLOWDOWN_RADIUS_M = 2.0
YAW_GAIN = 2.0
HIDDEN_SIZE = 8
OPSET = 17


def _const(name: str, value) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value, dtype=np.float32), name)


def build_goal_seeker() -> onnx.ModelProto:
    """The goal-seeker graph, with contract metadata, checked by ``onnx.checker``."""
    f32 = TensorProto.FLOAT
    size = c.IMAGE_SIZE_PX
    inputs = [
        helper.make_tensor_value_info(c.ONNX_INPUT_GRAY, f32, [1, 1, size, size]),
        helper.make_tensor_value_info(c.ONNX_INPUT_DEPTH, f32, [1, 1, size, size]),
        helper.make_tensor_value_info(c.ONNX_INPUT_STATE, f32, [1, c.STATE_DIM]),
        helper.make_tensor_value_info(c.ONNX_INPUT_HIDDEN, f32, [1, HIDDEN_SIZE]),
    ]
    outputs = [
        helper.make_tensor_value_info(c.ONNX_OUTPUT_ACTION, f32, [1, c.ACTION_DIM]),
        helper.make_tensor_value_info(c.ONNX_OUTPUT_HIDDEN, f32, [1, HIDDEN_SIZE]),
        helper.make_tensor_value_info(c.ONNX_OUTPUT_LATENT, f32, [1, c.LATENT_DIM]),
    ]
    goal_dist_scale_m = c.GOAL_DISTANCE_CLIP_M
    initializers = [
        numpy_helper.from_array(np.array([0], np.int64), "i0"),
        numpy_helper.from_array(np.array([1], np.int64), "i1"),
        numpy_helper.from_array(np.array([2], np.int64), "i2"),
        numpy_helper.from_array(np.array([3], np.int64), "i3"),
        numpy_helper.from_array(np.array([4], np.int64), "i4"),
        _const("zero", 0.0),
        _const("one", 1.0),
        _const("minus_one", -1.0),
        _const("eps", 1e-6),
        _const("yaw_gain", YAW_GAIN),
        _const("speed_per_action", c.MAX_SPEED_M_S / 2.0),
        _const("cruise_speed", CRUISE_SPEED_M_S),
        _const("dist_scale_over_slowdown", goal_dist_scale_m / SLOWDOWN_RADIUS_M),
        _const("inv_max_incl", 1.0 / c.MAX_INCLINATION_RAD),
        _const("latent_zeros", np.zeros((1, c.LATENT_DIM))),
    ]
    s = c.ONNX_INPUT_STATE
    nodes = [
        # Goal direction in V and normalised distance from the state vector.
        helper.make_node("Slice", [s, "i0", "i1", "i1"], ["gx"]),
        helper.make_node("Slice", [s, "i1", "i2", "i1"], ["gy"]),
        helper.make_node("Slice", [s, "i2", "i3", "i1"], ["gz"]),
        helper.make_node("Slice", [s, "i3", "i4", "i1"], ["dist_norm"]),
        # Horizontal bearing: cos = gx/|gxy|, sin = gy/|gxy|.
        helper.make_node("Mul", ["gx", "gx"], ["gx2"]),
        helper.make_node("Mul", ["gy", "gy"], ["gy2"]),
        helper.make_node("Add", ["gx2", "gy2"], ["gxy2"]),
        helper.make_node("Sqrt", ["gxy2"], ["gxy_raw"]),
        helper.make_node("Max", ["gxy_raw", "eps"], ["gxy"]),
        helper.make_node("Div", ["gx", "gxy"], ["cos_bearing"]),
        helper.make_node("Div", ["gy", "gxy"], ["sin_bearing"]),
        # Yaw: proportional to the bearing's sine ahead, full rate toward the goal's side behind.
        helper.make_node("Mul", ["sin_bearing", "yaw_gain"], ["yaw_p"]),
        helper.make_node("Less", ["gy", "zero"], ["goal_right"]),
        helper.make_node("Where", ["goal_right", "minus_one", "one"], ["yaw_full"]),
        helper.make_node("Greater", ["cos_bearing", "zero"], ["goal_ahead"]),
        helper.make_node("Where", ["goal_ahead", "yaw_p", "yaw_full"], ["yaw_raw"]),
        helper.make_node("Clip", ["yaw_raw", "minus_one", "one"], ["a_yaw"]),
        # Speed: cruise x max(cos, 0) x min(1, dist / slowdown radius) -> action a1 = speed - 1.
        helper.make_node("Max", ["cos_bearing", "zero"], ["facing"]),
        helper.make_node("Mul", ["dist_norm", "dist_scale_over_slowdown"], ["near_raw"]),
        helper.make_node("Min", ["near_raw", "one"], ["near"]),
        helper.make_node("Mul", ["facing", "near"], ["speed_frac"]),
        helper.make_node("Mul", ["speed_frac", "cruise_speed"], ["speed_m_s"]),
        helper.make_node("Div", ["speed_m_s", "speed_per_action"], ["speed_action_plus_one"]),
        helper.make_node("Sub", ["speed_action_plus_one", "one"], ["a_speed"]),
        # Inclination: elevation of the goal direction.
        helper.make_node("Clip", ["gz", "minus_one", "one"], ["gz_clipped"]),
        helper.make_node("Asin", ["gz_clipped"], ["elevation_rad"]),
        helper.make_node("Mul", ["elevation_rad", "inv_max_incl"], ["incl_raw"]),
        helper.make_node("Clip", ["incl_raw", "minus_one", "one"], ["a_incl"]),
        helper.make_node("Concat", ["a_speed", "a_incl", "a_yaw"], [c.ONNX_OUTPUT_ACTION], axis=1),
        helper.make_node("Identity", [c.ONNX_INPUT_HIDDEN], [c.ONNX_OUTPUT_HIDDEN]),
        helper.make_node("Identity", ["latent_zeros"], [c.ONNX_OUTPUT_LATENT]),
    ]
    graph = helper.make_graph(nodes, "cmnav_goal_seeker", inputs, outputs, initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="cmnav")
    model.ir_version = 8
    metadata = contract_metadata()
    metadata["cmnav.model"] = "goal-seeker"
    metadata["cmnav.description"] = (
        "ignores images; turns toward the goal and flies at "
        f"{CRUISE_SPEED_M_S} m/s, slowing within {SLOWDOWN_RADIUS_M} m (plumbing check)"
    )
    helper.set_model_props(model, metadata)
    onnx.checker.check_model(model, full_check=True)
    return model


def reference_action(state: np.ndarray) -> np.ndarray:
    """The same control law in numpy (used by tests to check the graph)."""
    gx, gy, gz, dist_norm = (float(v) for v in state[:4])
    gxy = max(math.hypot(gx, gy), 1e-6)
    cos_b, sin_b = gx / gxy, gy / gxy
    a_yaw = float(np.clip(YAW_GAIN * sin_b, -1, 1)) if cos_b > 0 else (-1.0 if gy < 0 else 1.0)
    speed = CRUISE_SPEED_M_S * max(cos_b, 0.0) * min(1.0, dist_norm * c.GOAL_DISTANCE_CLIP_M / SLOWDOWN_RADIUS_M)
    a_speed = speed / (c.MAX_SPEED_M_S / 2.0) - 1.0
    a_incl = float(np.clip(math.asin(float(np.clip(gz, -1, 1))) / c.MAX_INCLINATION_RAD, -1, 1))
    return np.array([a_speed, a_incl, a_yaw], dtype=np.float32)


def export_goal_seeker(path: str) -> None:
    """Write the goal-seeker to ``path`` (parent directories are created)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(build_goal_seeker(), str(out))
