"""The goal-seeker graph: contract signature and metadata, and its control law."""

import subprocess
import sys

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from export.goal_seeker import HIDDEN_SIZE, build_goal_seeker, reference_action
from runtime.contract import action_to_velocity_flu, check_contract_metadata
from runtime.contract import constants as c


@pytest.fixture(scope="module")
def session():
    return ort.InferenceSession(build_goal_seeker().SerializeToString(), providers=["CPUExecutionProvider"])


def _run(session, state, hidden=None):
    feeds = {
        c.ONNX_INPUT_GRAY: np.zeros((1, 1, 224, 224), np.float32),
        c.ONNX_INPUT_DEPTH: np.zeros((1, 1, 224, 224), np.float32),
        c.ONNX_INPUT_STATE: state.reshape(1, -1).astype(np.float32),
        c.ONNX_INPUT_HIDDEN: np.zeros((1, HIDDEN_SIZE), np.float32) if hidden is None else hidden,
    }
    return dict(zip([o.name for o in session.get_outputs()], session.run(None, feeds)))


def test_signature_and_metadata(session):
    names = [i.name for i in session.get_inputs()]
    assert names == [c.ONNX_INPUT_GRAY, c.ONNX_INPUT_DEPTH, c.ONNX_INPUT_STATE, c.ONNX_INPUT_HIDDEN]
    assert [o.name for o in session.get_outputs()] == [
        c.ONNX_OUTPUT_ACTION,
        c.ONNX_OUTPUT_HIDDEN,
        c.ONNX_OUTPUT_LATENT,
    ]
    check_contract_metadata(session.get_modelmeta().custom_metadata_map)


unit = st.floats(-1, 1, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(unit, unit, unit, st.floats(0, 1))
def test_graph_matches_reference(session, gx, gy, gz, dist):
    norm = np.sqrt(gx * gx + gy * gy + gz * gz)
    g = np.array([gx, gy, gz]) / norm if norm > 1e-3 else np.array([1.0, 0.0, 0.0])
    state = np.zeros(c.STATE_DIM, np.float32)
    state[:3], state[3] = g, dist
    out = _run(session, state)
    np.testing.assert_allclose(out[c.ONNX_OUTPUT_ACTION][0], reference_action(state), atol=1e-5)
    assert np.all(np.abs(out[c.ONNX_OUTPUT_ACTION]) <= 1.0)


def test_steering_signs(session):
    state = np.zeros(c.STATE_DIM, np.float32)
    state[3] = 0.5
    state[:3] = [0.0, 1.0, 0.0]  # goal to the left
    assert _run(session, state)[c.ONNX_OUTPUT_ACTION][0, 2] > 0  # positive yaw = turn left
    state[:3] = [-1.0, -0.01, 0.0]  # goal behind, slightly right: turn right at full rate, no speed
    action = _run(session, state)[c.ONNX_OUTPUT_ACTION][0]
    assert action[2] == -1.0 and action[0] == pytest.approx(-1.0)
    state[:3] = [np.sqrt(0.5), 0.0, np.sqrt(0.5)]  # ahead and above: climb
    vx, _, vz, wz = action_to_velocity_flu(_run(session, state)[c.ONNX_OUTPUT_ACTION][0])
    assert vz > 0 and vx > 0 and wz == 0


def test_hidden_passthrough_and_zero_latent(session):
    hidden = np.arange(HIDDEN_SIZE, dtype=np.float32).reshape(1, -1)
    state = np.zeros(c.STATE_DIM, np.float32)
    state[0] = 1.0
    out = _run(session, state, hidden)
    np.testing.assert_array_equal(out[c.ONNX_OUTPUT_HIDDEN], hidden)
    assert out[c.ONNX_OUTPUT_LATENT].shape == (1, c.LATENT_DIM) and not out[c.ONNX_OUTPUT_LATENT].any()


def test_cli_writes_a_loadable_model(tmp_path):
    path = tmp_path / "nested" / "gs.onnx"
    subprocess.run([sys.executable, "-m", "cmnav", "export", "goal-seeker", "-o", str(path)], check=True)
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    assert {p.key: p.value for p in model.metadata_props}["cmnav.model"] == "goal-seeker"
