"""`cmnav fly`'s model selection and placement: ``policy.variant`` picks the export that flies,
the provider list falls back from TensorRT/CUDA to ONNX Runtime's CPU provider and the model is
warmed up before READY, and ``runtime.cpu_affinity`` is validated and pins every thread."""

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import onnxruntime as ort
import pytest

from runtime.config import ConfigError, ProcessConfig, TensorRtConfig, variant_path
from runtime.config_loader import load_config
from runtime.contract import contract_metadata
from runtime.programs.fly import FlyError, load_model
from runtime.model import KEY_VARIANT, ModelLoadError, session_providers
from tests.runtime.onnx_models import save, step_model

ROOT = Path(__file__).resolve().parents[2]
MISSION = "[mission]\ngoal_rel_home_enu_m = [5.0, 0.0, 1.5]\n"
ALLOWED = sorted(os.sched_getaffinity(0))


def _config(tmp_path: Path, policy: str = "", extra: str = "") -> Path:
    path = tmp_path / "cmnav.toml"
    path.write_text(f'[policy]\nmodel_path = "model.onnx"\n{policy}\n{MISSION}{extra}')
    return path


@pytest.fixture
def models(tmp_path) -> Path:
    """model.onnx (fp32) and its int8 variant next to it (metadata naming it), in tmp_path."""
    save(step_model(), tmp_path / "model.onnx")
    save(step_model(metadata={**contract_metadata(), KEY_VARIANT: "int8"}), variant_path(tmp_path / "model.onnx", "int8"))
    return tmp_path / "model.onnx"


def test_variant_selects_the_file_next_to_the_model(models, tmp_path):
    config = load_config(_config(tmp_path, 'variant = "int8"\nwarmup_steps = 0'))
    assert config.policy.model_file == tmp_path / "model.int8.onnx"
    model = load_model(config)
    assert model.path == tmp_path / "model.int8.onnx" and model.variant == "int8"
    assert model.log_metadata()["model_variant"] == "int8"
    assert load_model(load_config(_config(tmp_path, "warmup_steps = 0"))).variant == "fp32"


def test_variant_errors_name_the_key(models, tmp_path):
    with pytest.raises(ConfigError, match=r"policy\.variant='int4' is invalid: must be one of fp32, fp16, int8"):
        load_config(_config(tmp_path, 'variant = "int4"'))
    with pytest.raises(ConfigError, match=r"policy\.variant = 'fp16': no .*model\.fp16\.onnx next to policy\.model_path"):
        load_config(_config(tmp_path, 'variant = "fp16"'))
    # A file under the variant's name that is another export is refused at load, nothing armed.
    save(step_model(), variant_path(models, "fp16"))
    with pytest.raises(FlyError, match=r"model\.fp16\.onnx is the fp32 export .*not the fp16 one policy\.variant names"):
        load_model(load_config(_config(tmp_path, 'variant = "fp16"')))


@pytest.mark.skipif(
    {"TensorrtExecutionProvider", "CUDAExecutionProvider"} & set(ort.get_available_providers()),
    reason="a GPU provider is available here: no fallback to show",
)
def test_gpu_providers_fall_back_to_cpu_and_the_model_is_warmed_up(models, tmp_path, caplog):
    policy = ('providers = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]\n'
              'provider_fallback = true\nwarmup_steps = 4\n[policy.tensorrt]\nengine_cache_dir = "trt-cache"\nfp16 = false')  # fmt: skip
    config = load_config(_config(tmp_path, policy))
    assert config.policy.tensorrt.engine_cache_dir == tmp_path / "trt-cache"  # relative to the config file
    caplog.set_level(logging.INFO)
    model = load_model(config)
    assert model.providers == ("CPUExecutionProvider",)
    assert "['TensorrtExecutionProvider', 'CUDAExecutionProvider'] not available; falling back to ['CPUExecutionProvider']" in caplog.text
    assert "warm-up on ('CPUExecutionProvider',): 4 steps" in caplog.text
    assert len(model.warm_up(2)) == 2
    assert not (tmp_path / "trt-cache").exists()  # TensorRT did not run: no engine cache made


def test_tensorrt_gets_fp16_and_its_engine_cache(tmp_path):
    cache = tmp_path / "state" / "trt"
    providers = session_providers(("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
                                  TensorRtConfig(fp16=True, engine_cache_dir=cache, max_workspace_mb=256))  # fmt: skip
    name, options = providers[0]
    assert name == "TensorrtExecutionProvider" and providers[1:] == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert options["trt_fp16_enable"] is True and options["trt_engine_cache_enable"] is True
    assert options["trt_engine_cache_path"] == str(cache) == options["trt_timing_cache_path"] and cache.is_dir()
    assert options["trt_max_workspace_size"] == 256 << 20
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    with pytest.raises(ModelLoadError, match=r"policy\.tensorrt\.engine_cache_dir .*a-file/trt cannot be created"):
        session_providers(("TensorrtExecutionProvider",), TensorRtConfig(engine_cache_dir=blocked / "trt"))
    with pytest.raises(ConfigError, match=r"policy\.tensorrt\.max_workspace_mb=8 is invalid: must be an integer in \[64, 65536\]"):
        TensorRtConfig(max_workspace_mb=8)


def test_cpu_affinity_is_validated(models, tmp_path):
    assert load_config(_config(tmp_path, extra=f"[runtime]\ncpu_affinity = [{ALLOWED[0]}]\n")).runtime.cpu_affinity == (ALLOWED[0],)
    assert load_config(_config(tmp_path)).runtime.cpu_affinity == ()
    outside = max(ALLOWED) + 1
    with pytest.raises(ConfigError, match=rf"runtime\.cpu_affinity=\[{outside}\] is invalid: must be CPU ids this process may run on: "
                                          rf"\[{', '.join(map(str, ALLOWED))}\]"):  # fmt: skip
        load_config(_config(tmp_path, extra=f"[runtime]\ncpu_affinity = [{outside}]\n"))
    with pytest.raises(ConfigError, match=r"runtime\.cpu_affinity=\[0, 0\] is invalid: must be a list of distinct integer CPU ids"):
        ProcessConfig(cpu_affinity=(0, 0))
    with pytest.raises(ConfigError, match=r"runtime\.cpu_affinity\[0\] = 'one' is a string: must be an integer"):
        load_config(_config(tmp_path, extra='[runtime]\ncpu_affinity = ["one"]\n'))
    with pytest.raises(ConfigError, match=r"policy\.intra_op_threads=2 is invalid: must be <= the 1 CPU\(s\) of runtime\.cpu_affinity"):
        load_config(_config(tmp_path, "intra_op_threads = 2", extra=f"[runtime]\ncpu_affinity = [{ALLOWED[0]}]\n"))


def test_pin_process_pins_every_thread():
    """In a child process (pinning this one would slow every later test): threads started before
    and after the pin all end up on the one CPU."""
    cpu = ALLOWED[-1]
    code = f"""
import json, os, threading, time
from runtime.service.affinity import pin_process
stop = threading.Event()
before = threading.Thread(target=stop.wait); before.start()
pinned = pin_process([{cpu}])
after = threading.Thread(target=stop.wait); after.start()
sets = [sorted(os.sched_getaffinity(int(t))) for t in os.listdir("/proc/self/task")]
stop.set(); before.join(); after.join()
print(json.dumps({{"pinned": pinned, "threads": sets}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["pinned"] == [cpu] and len(out["threads"]) >= 3 and all(s == [cpu] for s in out["threads"])


def test_control_process_set_up():
    """In a child process: the control process gets the short GIL switch interval (and is pinned
    when CPUs are given)."""
    cpu = ALLOWED[-1]
    code = f"""
import json, sys
from runtime.service.affinity import GIL_SWITCH_INTERVAL_S, prepare_control_process
unpinned = prepare_control_process(None)
pinned = prepare_control_process([{cpu}])
print(json.dumps({{"unpinned": unpinned, "pinned": pinned, "interval": sys.getswitchinterval(),
                  "wanted": GIL_SWITCH_INTERVAL_S}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["unpinned"] is None and out["pinned"] == [cpu]
    assert out["interval"] == pytest.approx(out["wanted"]) and out["wanted"] < 0.005  # CPython's default is 5 ms
