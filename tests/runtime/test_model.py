import json

import numpy as np
import pytest
from onnx import TensorProto

from runtime.contract import ContractMismatchError, contract_metadata
from runtime.contract import constants as c
from runtime.contract.metadata import METADATA_KEY_VALUES, METADATA_KEY_VERSION
from runtime.model import ModelLoadError, PolicyModel, ProviderUnavailableError, check_outputs_finite
from tests.runtime.onnx_models import default_inputs, default_outputs, save, step_model


def _inputs(**changes):
    return [(n, changes.get(n, (s, t))[0], changes.get(n, (s, t))[1]) for n, s, t in default_inputs(8)]


def _outputs(**changes):
    return [(n, changes.get(n, (s, t))[0], changes.get(n, (s, t))[1]) for n, s, t in default_outputs(8)]


def test_good_model_steps(tmp_path):
    model = PolicyModel(save(step_model(hidden_size=12), tmp_path / "m.onnx"))
    assert model.hidden_size == 12
    assert model.providers == ("CPUExecutionProvider",)
    hidden = model.initial_hidden()
    assert hidden.shape == (12,) and not hidden.any()
    state = np.linspace(-1, 1, c.STATE_DIM, dtype=np.float32)
    gray = np.full((224, 224), 0.25, np.float32)
    depth = np.full((224, 224), 0.5, np.float32)
    out = model.step(gray, depth, state, hidden)
    np.testing.assert_allclose(out.action, np.tanh(state[:3]), rtol=1e-6)
    np.testing.assert_allclose(out.hidden_next, np.ones(12))
    assert out.latent.shape == (64,)
    np.testing.assert_allclose(out.latent, 0.75, rtol=1e-6)


def test_step_input_shape_checked(tmp_path):
    model = PolicyModel(save(step_model(), tmp_path / "m.onnx"))
    with pytest.raises(ValueError, match="'state' has shape \\(14,\\), expected \\(15,\\)"):
        model.step(np.zeros((224, 224)), np.zeros((224, 224)), np.zeros(14), model.initial_hidden())


def test_missing_file_named(tmp_path):
    with pytest.raises(ModelLoadError, match="nope.onnx does not exist"):
        PolicyModel(tmp_path / "nope.onnx")


def test_not_onnx_named(tmp_path):
    path = tmp_path / "junk.onnx"
    path.write_bytes(b"this is not a protobuf")
    with pytest.raises(ModelLoadError, match="not a loadable ONNX model"):
        PolicyModel(path)


def test_unavailable_provider_named(tmp_path):
    path = save(step_model(), tmp_path / "m.onnx")
    with pytest.raises(ProviderUnavailableError, match="TensorrtExecutionProvider.*available"):
        PolicyModel(path, providers=("TensorrtExecutionProvider", "CPUExecutionProvider"))


@pytest.mark.parametrize(
    "inputs, outputs, message",
    [
        (
            [("image", [1, 1, 224, 224], TensorProto.FLOAT)] + _inputs()[1:],
            None,
            "unexpected input 'image'.*missing input 'gray'",
        ),
        (_inputs(depth=([1, 1, 128, 128], TensorProto.FLOAT)), None, "input 'depth' has shape \\[1, 1, 128, 128\\]"),
        (_inputs(state=([1, 15], TensorProto.DOUBLE)), None, "input 'state' has type tensor\\(double\\)"),
        (_inputs(state=([2, 15], TensorProto.FLOAT)), None, "input 'state' has batch size 2"),
        (_inputs(hidden=([1, "h"], TensorProto.FLOAT)), None, "hidden size 'h'.*fixed integer"),
        (None, _outputs(hidden_next=([1, 16], TensorProto.FLOAT)), "GRU hidden sizes differ"),
        (None, _outputs(latent=([1, 32], TensorProto.FLOAT)), "output 'latent' has shape \\[1, 32\\], expected \\[1, 64\\]"),
        (None, _outputs()[:2], "missing output 'latent'"),
    ],
)
def test_wrong_signature_named(tmp_path, inputs, outputs, message):
    path = save(step_model(inputs=inputs, outputs=outputs), tmp_path / "bad.onnx")
    with pytest.raises(ModelLoadError, match=message):
        PolicyModel(path)


def test_symbolic_batch_accepted(tmp_path):
    inputs = [(n, ["batch"] + s[1:], t) for n, s, t in default_inputs(8)]
    model = PolicyModel(save(step_model(inputs=inputs), tmp_path / "m.onnx"))
    assert model.hidden_size == 8


def test_missing_contract_metadata_named(tmp_path):
    path = save(step_model(metadata={}), tmp_path / "m.onnx")
    with pytest.raises(ContractMismatchError, match="carries no cmnav contract metadata"):
        PolicyModel(path)


def test_mismatched_contract_named(tmp_path):
    meta = contract_metadata()
    values = json.loads(meta[METADATA_KEY_VALUES])
    values["max_speed_m_s"] = 3.0
    meta[METADATA_KEY_VALUES] = json.dumps(values)
    meta[METADATA_KEY_VERSION] = "0"
    path = save(step_model(metadata=meta), tmp_path / "m.onnx")
    with pytest.raises(ContractMismatchError, match="contract version '0'.*max_speed_m_s: .* has 3.0, runtime has 2.0"):
        PolicyModel(path)


def test_good_model_passes_the_output_check(tmp_path):
    check_outputs_finite(PolicyModel(save(step_model(), tmp_path / "good.onnx")))


def test_nan_model_is_refused_before_it_flies(tmp_path):
    model = PolicyModel(save(step_model(action_offset=float("nan")), tmp_path / "nan.onnx"))
    with pytest.raises(ModelLoadError, match=r"outputs NaN/Inf \(action\) on all-zero inputs"):
        check_outputs_finite(model)


def test_unknown_opset_is_refused_on_one_line(tmp_path):
    model = step_model()
    model.opset_import[0].version = 99  # ONNX Runtime's refusal spans several lines
    path = tmp_path / "opset99.onnx"
    path.write_bytes(model.SerializeToString())
    with pytest.raises(ModelLoadError, match="not a loadable ONNX model") as info:
        PolicyModel(path)
    assert "\n" not in str(info.value)
