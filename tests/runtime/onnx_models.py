"""Tiny ONNX graphs with the runtime's step signature (or deliberately wrong ones), for tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from runtime.contract import constants as c
from runtime.contract import contract_metadata

SIZE = c.IMAGE_SIZE_PX


def default_inputs(hidden_size: int) -> list[tuple[str, list, int]]:
    f32 = TensorProto.FLOAT
    return [
        (c.ONNX_INPUT_GRAY, [1, 1, SIZE, SIZE], f32),
        (c.ONNX_INPUT_DEPTH, [1, 1, SIZE, SIZE], f32),
        (c.ONNX_INPUT_STATE, [1, c.STATE_DIM], f32),
        (c.ONNX_INPUT_HIDDEN, [1, hidden_size], f32),
    ]


def default_outputs(hidden_size: int) -> list[tuple[str, list, int]]:
    f32 = TensorProto.FLOAT
    return [
        (c.ONNX_OUTPUT_ACTION, [1, c.ACTION_DIM], f32),
        (c.ONNX_OUTPUT_HIDDEN, [1, hidden_size], f32),
        (c.ONNX_OUTPUT_LATENT, [1, c.LATENT_DIM], f32),
    ]


def step_model(
    hidden_size: int = 8,
    inputs: list[tuple[str, list, int]] | None = None,
    outputs: list[tuple[str, list, int]] | None = None,
    metadata: dict[str, str] | None = None,
    action_offset: float = 0.0,
) -> onnx.ModelProto:
    """A step graph.  With the default signature it computes
    action = tanh(state[0:3]) + action_offset (NaN makes a NaN action), hidden_next = hidden + 1, latent = mean(depth) + mean(gray) (x64);
    with an overridden signature every output is a constant (the graph only has to load)."""
    inputs = default_inputs(hidden_size) if inputs is None else inputs
    outputs = default_outputs(hidden_size) if outputs is None else outputs
    in_infos = [helper.make_tensor_value_info(n, t, s) for n, s, t in inputs]
    out_infos = [helper.make_tensor_value_info(n, t, s) for n, s, t in outputs]
    if inputs == default_inputs(hidden_size) and outputs == default_outputs(hidden_size):
        inits = [
            numpy_helper.from_array(np.array([0], np.int64), "i0"),
            numpy_helper.from_array(np.array([3], np.int64), "i3"),
            numpy_helper.from_array(np.array([1], np.int64), "i1"),
            numpy_helper.from_array(np.array([2, 3], np.int64), "axes_hw"),
            numpy_helper.from_array(np.ones((1, c.LATENT_DIM), np.float32), "ones_latent"),
            numpy_helper.from_array(np.ones((1,), np.float32), "one"),
            numpy_helper.from_array(np.full((1,), action_offset, np.float32), "action_offset"),
        ]
        nodes = [
            helper.make_node("Slice", [c.ONNX_INPUT_STATE, "i0", "i3", "i1"], ["s03"]),
            helper.make_node("Tanh", ["s03"], ["tanh_s03"]),
            helper.make_node("Add", ["tanh_s03", "action_offset"], [c.ONNX_OUTPUT_ACTION]),
            helper.make_node("Add", [c.ONNX_INPUT_HIDDEN, "one"], [c.ONNX_OUTPUT_HIDDEN]),
            helper.make_node("ReduceMean", [c.ONNX_INPUT_DEPTH, "axes_hw"], ["depth_mean"], keepdims=0),
            helper.make_node("ReduceMean", [c.ONNX_INPUT_GRAY, "axes_hw"], ["gray_mean"], keepdims=0),
            helper.make_node("Add", ["depth_mean", "gray_mean"], ["img_mean"]),
            helper.make_node("Mul", ["img_mean", "ones_latent"], [c.ONNX_OUTPUT_LATENT]),
        ]
    else:
        inits, nodes = [], []
        for name, shape, elem_type in outputs:
            concrete = [d if isinstance(d, int) else 1 for d in shape]
            dtype = helper.tensor_dtype_to_np_dtype(elem_type)
            inits.append(numpy_helper.from_array(np.zeros(concrete, dtype), f"{name}_const"))
            nodes.append(helper.make_node("Identity", [f"{name}_const"], [name]))
    graph = helper.make_graph(nodes, "test_step", in_infos, out_infos, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    helper.set_model_props(model, contract_metadata() if metadata is None else metadata)
    onnx.checker.check_model(model)
    return model


def save(model: onnx.ModelProto, path: Path) -> Path:
    onnx.save(model, str(path))
    return path


def recurrent_step_model(hidden_size: int = 8, action_offset: float = 0.0) -> onnx.ModelProto:
    """A step graph whose action depends on everything replay must carry right: the goal direction
    (state[0:3]), the previous action (state[12:15]) and the GRU state, which in turn follows the
    images.  action = tanh(state[0:3] + hidden[0:3] + 0.5 state[12:15]) + action_offset;
    hidden_next = 0.5 hidden + mean(depth) + mean(gray); latent = (mean(depth) + mean(gray)) x 64."""
    inits = [
        numpy_helper.from_array(np.array([0], np.int64), "i0"),
        numpy_helper.from_array(np.array([3], np.int64), "i3"),
        numpy_helper.from_array(np.array([12], np.int64), "i12"),
        numpy_helper.from_array(np.array([15], np.int64), "i15"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
        numpy_helper.from_array(np.array([2, 3], np.int64), "axes_hw"),
        numpy_helper.from_array(np.ones((1, c.LATENT_DIM), np.float32), "ones_latent"),
        numpy_helper.from_array(np.full((1,), 0.5, np.float32), "half"),
        numpy_helper.from_array(np.full((1,), action_offset, np.float32), "action_offset"),
    ]
    nodes = [
        helper.make_node("Slice", [c.ONNX_INPUT_STATE, "i0", "i3", "axis1"], ["goal_dir"]),
        helper.make_node("Slice", [c.ONNX_INPUT_STATE, "i12", "i15", "axis1"], ["prev_action"]),
        helper.make_node("Slice", [c.ONNX_INPUT_HIDDEN, "i0", "i3", "axis1"], ["h03"]),
        helper.make_node("Mul", ["prev_action", "half"], ["half_prev"]),
        helper.make_node("Add", ["goal_dir", "h03"], ["pre0"]),
        helper.make_node("Add", ["pre0", "half_prev"], ["pre1"]),
        helper.make_node("Tanh", ["pre1"], ["tanh_pre"]),
        helper.make_node("Add", ["tanh_pre", "action_offset"], [c.ONNX_OUTPUT_ACTION]),
        helper.make_node("ReduceMean", [c.ONNX_INPUT_DEPTH, "axes_hw"], ["depth_mean"], keepdims=0),
        helper.make_node("ReduceMean", [c.ONNX_INPUT_GRAY, "axes_hw"], ["gray_mean"], keepdims=0),
        helper.make_node("Add", ["depth_mean", "gray_mean"], ["img_mean"]),
        helper.make_node("Mul", [c.ONNX_INPUT_HIDDEN, "half"], ["half_hidden"]),
        helper.make_node("Add", ["half_hidden", "img_mean"], [c.ONNX_OUTPUT_HIDDEN]),
        helper.make_node("Mul", ["img_mean", "ones_latent"], [c.ONNX_OUTPUT_LATENT]),
    ]
    in_infos = [helper.make_tensor_value_info(n, t, s) for n, s, t in default_inputs(hidden_size)]
    out_infos = [helper.make_tensor_value_info(n, t, s) for n, s, t in default_outputs(hidden_size)]
    graph = helper.make_graph(nodes, "recurrent_test_step", in_infos, out_infos, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    helper.set_model_props(model, contract_metadata())
    onnx.checker.check_model(model)
    return model
