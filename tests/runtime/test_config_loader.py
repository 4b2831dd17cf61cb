"""The TOML config of `cmnav fly`: the shipped examples load, and every bad value is named."""

import dataclasses
import re
import shutil
import typing
from pathlib import Path

import pytest

from runtime.config import RuntimeConfig
from runtime.config_loader import ConfigError, load_config
from runtime.model import file_sha256
from tests.runtime.onnx_models import save, step_model

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return save(step_model(), tmp_path_factory.mktemp("model") / "model.onnx")


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cmnav.toml"
    path.write_text(text)
    return path


def _minimal(model: Path, extra: str = "", mission: str = "") -> str:
    return f'[policy]\nmodel_path = "{model}"\n{extra}\n[mission]\ngoal_rel_home_enu_m = [5.0, 0.0, 1.5]\n{mission}\n'


def _field_example(model: Path, log_dir: Path | None = None) -> str:
    """examples/cmnav.toml with its model path pointed at a real model (and its log directory,
    /var/log/cmnav on the Jetson, at ``log_dir``: the loader checks it is writable)."""
    text = (EXAMPLES / "cmnav.toml").read_text()
    text, n = re.subn(r'^model_path = ".*"', f'model_path = "{model}"', text, flags=re.M)
    assert n == 1
    if log_dir is not None:
        text, n = re.subn(r'^log_dir = ".*"', f'log_dir = "{log_dir}"', text, flags=re.M)
        assert n == 1
    return text


def test_field_example_loads(model, tmp_path):
    assert 'log_dir = "/var/log/cmnav"' in (EXAMPLES / "cmnav.toml").read_text()
    config = load_config(_write(tmp_path, _field_example(model, tmp_path / "logs")))
    assert config.policy.model_path == model
    assert config.policy.providers == ("CUDAExecutionProvider", "CPUExecutionProvider")
    assert config.policy.limits.max_speed_m_s == 1.0 and config.mission.allow_arm_takeoff is False
    assert config.recorder.log_dir == tmp_path / "logs" and config.camera.source == "realsense"
    assert config.vehicle.url == "udpin://0.0.0.0:14540"


def _dataclass_keys(cls: type, prefix: str = "") -> list[tuple[str, str]]:
    """(table, key) of every field of ``cls`` and the dataclasses it nests."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            out += _dataclass_keys(hints[f.name], f"{prefix}{f.name}.")
        else:
            out.append((prefix.rstrip("."), f.name))
    return out


def test_field_example_documents_every_key():
    """Every config field appears in examples/cmnav.toml (commented out when it has no default
    value to show), in its table, with a comment."""
    text = (EXAMPLES / "cmnav.toml").read_text()
    tables: dict[str, list[str]] = {}
    table = ""
    for line in text.splitlines():
        header = re.match(r"^\[([\w.]+)\]", line)
        if header:
            table = header.group(1)
        tables.setdefault(table, []).append(line)
    missing = []
    for table, key in _dataclass_keys(RuntimeConfig):
        lines = tables.get(table, [])
        at = [i for i, line in enumerate(lines) if re.match(rf"^#?\s*{key}\s*=", line)]
        documented = at and ("#" in lines[at[0]].split("=", 1)[1] or lines[at[0]].startswith("#") or lines[at[0] - 1].startswith("#"))
        if not documented:
            missing.append(f"{table}.{key}")
    assert not missing, f"keys not documented in examples/cmnav.toml: {missing}"


def test_sitl_example_loads(model, tmp_path):
    (tmp_path / "examples").mkdir()
    (tmp_path / "runs" / "models").mkdir(parents=True)
    shutil.copy(EXAMPLES / "sitl.toml", tmp_path / "examples" / "sitl.toml")
    shutil.copy(model, tmp_path / "runs" / "models" / "goal-seeker.onnx")
    config = load_config(tmp_path / "examples" / "sitl.toml")
    assert config.mission.allow_arm_takeoff and config.mission.max_episodes == 1
    assert config.camera.source == "sim" and config.camera.sim.port == 5600
    # Relative paths are relative to the config file's folder.
    assert config.policy.model_path.resolve() == (tmp_path / "runs" / "models" / "goal-seeker.onnx").resolve()
    assert config.recorder.log_dir.resolve() == (tmp_path / "runs" / "fly-sitl").resolve()


def test_defaults_fill_what_is_left_out(model, tmp_path):
    config = load_config(_write(tmp_path, _minimal(model)))
    assert config.watchdog == RuntimeConfig().watchdog and config.vehicle == RuntimeConfig().vehicle
    assert config.mission.goal_rel_home_enu_m == (5.0, 0.0, 1.5)


def test_sha256_that_matches_is_accepted(model, tmp_path):
    config = load_config(_write(tmp_path, _minimal(model, f'model_sha256 = "{file_sha256(model).upper()}"')))
    assert config.policy.model_sha256 is not None


POLICY = '[policy]\nmodel_path = "{model}"\n'
MISSION = "[mission]\ngoal_rel_home_enu_m = [5.0, 0.0, 1.5]\n"
# case: (config text, with {model} = a real model file; what the error must say)
BAD = {
    "unknown key": (POLICY + MISSION + "[watchdog]\nframe_stale_msec = 100\n",
                    r"unknown key watchdog\.frame_stale_msec .*did you mean watchdog\.frame_stale_ms\?"),
    "unknown table": (POLICY + MISSION + "[camera.kinect]\nport = 1\n",
                      r"unknown key camera\.kinect .*allowed: source, first_frame_timeout_s, realsense, sim, replay"),
    "wrong type": (POLICY + MISSION + '[watchdog]\nframe_stale_ms = "fast"\n',
                   r"watchdog\.frame_stale_ms = 'fast' is a string: must be a number"),
    "int for bool": (POLICY + MISSION + "[camera.realsense]\nemitter_enabled = 1\n",
                     r"camera\.realsense\.emitter_enabled = 1 is an integer: must be true or false"),
    "list length": (POLICY + "[mission]\ngoal_rel_home_enu_m = [1.0, 2.0]\n",
                    r"mission\.goal_rel_home_enu_m = \[1\.0, 2\.0\] has 2 values: must be a list of 3 numbers"),
    "table expected": ("policy = 3\n" + MISSION, r"policy must be a table"),
    "out of range": (POLICY + MISSION + "[watchdog]\ndepth_invalid_frac_max = 1.5\n",
                     r"watchdog\.depth_invalid_frac_max=1\.5 is invalid: must be in \(0, 1\]"),
    "looser speed": (POLICY + "[policy.limits]\nmax_speed_m_s = 3.0\n" + MISSION,
                     r"policy\.limits\.max_speed_m_s=3\.0 must be in \[0, 2\.0\].*never looser"),
    "looser inclination": (POLICY + "[policy.limits]\nmax_inclination_rad = 1.0\n" + MISSION,
                           r"policy\.limits\.max_inclination_rad=1\.0 must be in \[0, 0\.785398\]"),
    "bad sha256": (POLICY + 'model_sha256 = "abc"\n' + MISSION,
                   r"policy\.model_sha256='abc' is invalid: must be 64 hexadecimal digits"),
    "wrong sha256": (POLICY + 'model_sha256 = "' + "0" * 64 + '"\n' + MISSION,
                     r"policy\.model_sha256 = '0{64}' but .* has SHA-256 [0-9a-f]{64}"),
    "missing model": ('[policy]\nmodel_path = "/nonexistent/model.onnx"\n' + MISSION,
                      r"policy\.model_path = '/nonexistent/model\.onnx': no such file"),
    "unknown provider": (POLICY + 'providers = ["CudaProvider"]\n' + MISSION,
                         r"policy\.providers: unknown execution provider\(s\) \['CudaProvider'\]"),
    "bad url": (POLICY + MISSION + '[vehicle]\nurl = "udp://1.2.3.4:5"\n',
                r"vehicle\.url='udp://1\.2\.3\.4:5' is invalid: must be a MAVSDK connection URL"),
    "camera fps": (POLICY + MISSION + "[camera.realsense]\nfps = 30\n", r"camera\.realsense\.fps=30 is invalid: must be 15"),
    "sim without port": (POLICY + MISSION + '[camera]\nsource = "sim"\n', r"camera\.sim\.port=0 is invalid: must be a TCP port"),
    "goal outside fence": (POLICY + "[mission]\ngoal_rel_home_enu_m = [30.0, 0.0, 1.5]\n",
                           r"mission\.goal_rel_home_enu_m=\(30\.0, 0\.0, 1\.5\) is invalid: must be horizontally within watchdog\.geofence_radius_m"),
    "dry run episodes": (POLICY + MISSION + "allow_arm_takeoff = true\nmax_episodes = 2\n",
                         r"mission\.max_episodes=2 is invalid: must be 0 or 1 with allow_arm_takeoff = true"),
    "syntax": (POLICY + MISSION + "[watchdog\nx = 1\n", r"is not valid TOML"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD))
def test_bad_config_names_the_key(case, model, tmp_path):
    text, message = BAD[case]
    with pytest.raises(ConfigError, match=message):
        load_config(_write(tmp_path, text.replace("{model}", str(model))))


def test_missing_goal_is_named(model, tmp_path):
    with pytest.raises(ConfigError, match=r"mission\.goal_rel_home_enu_m is missing"):
        load_config(_write(tmp_path, f'[policy]\nmodel_path = "{model}"\n'))


def test_unreadable_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config file .*nope.toml"):
        load_config(tmp_path / "nope.toml")


# A hostile newcomer's configs (issue 13): values that would switch a safety check off, crash the
# checker or hang it are refused with one line naming the file and the key.
HOSTILE = {
    "watchdog period of an hour": ("[watchdog]\nperiod_s = 3600\n", r"watchdog\.period_s=3600\.0 is invalid: must be in \[0\.001, 0\.0666667\] s"),
    "frames stale for ever": ("[watchdog]\nframe_stale_ms = 1e9\n", r"watchdog\.frame_stale_ms=1000000000\.0 is invalid: must be in \[66\.6667, 1000\] ms"),
    "hover for ever": ("[watchdog]\nhold_grace_s = 1e6\n", r"watchdog\.hold_grace_s=1000000\.0 is invalid: must be in \[0, 5\] s"),
    "threads beyond int32": ("[policy]\nintra_op_threads = 2147483648\n", r"policy\.intra_op_threads=2147483648 is invalid: must be an integer in \[0, \d+\]"),
    "ten thousand threads": ("[policy]\nintra_op_threads = 10000\n", r"policy\.intra_op_threads=10000 is invalid"),
    "camera size no D455 has": ("[camera.realsense]\nwidth_px = 8480\nheight_px = 4800\n", r"camera\.realsense\.width_px x height_px = 8480x4800 is invalid: must be a D455 mode"),
    "url without host": ('[vehicle]\nurl = "udpin://:14540"\n', r"vehicle\.url='udpin://:14540' is invalid: .*no HOST:PORT"),
    "url with a bad port": ('[vehicle]\nurl = "udpout://127.0.0.1:99999"\n', r"vehicle\.url=.* port '99999' is not in 1\.\.65535"),
    "url with a bad host": ('[vehicle]\nurl = "tcpout://bad host!:5760"\n', r"vehicle\.url=.* host 'bad host!' is neither"),
    "serial url without device": ('[vehicle]\nurl = "serial://ttyTHS1:921600"\n', r"vehicle\.url=.* serial device 'ttyTHS1' is not a /dev path"),
    "command timeout of a day": ("[vehicle]\ncommand_timeout_s = 86400\n", r"vehicle\.command_timeout_s=86400\.0 is invalid: must be in \[0, 10\] s"),
    "log dir under /proc": ('[recorder]\nlog_dir = "/proc/cmnav-logs"\n', r"recorder\.log_dir = '/proc/cmnav-logs': cannot create anything in /proc"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_values_are_refused_naming_file_and_key(case, model, tmp_path):
    table, message = HOSTILE[case]
    section = table.split("]", 1)[0] + "]"
    text = _minimal(model) if section == "[policy]" else _minimal(model) + "\n" + table
    if section == "[policy]":  # one [policy] table: add the key to it
        text = text.replace("[policy]\n", table)
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_log_dir_that_is_a_file_is_refused(model, tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    with pytest.raises(ConfigError, match=r"recorder\.log_dir = .*not-a-dir' is a file, not a directory|not-a-dir is a file, not a directory"):
        load_config(_write(tmp_path, _minimal(model) + f'\n[recorder]\nlog_dir = "{blocker}"\n'))


def test_deeply_nested_and_huge_files_are_refused_with_a_line(model, tmp_path):
    deep = _write(tmp_path, "x = " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(ConfigError, match=r"nests .*too deeply|nests \d+ levels") as info:
        load_config(deep)
    assert str(info.value).startswith(str(deep))
    huge = tmp_path / "huge.toml"
    huge.write_text(_minimal(model) + '[vehicle]\nurl = "udpin://' + "a" * 5_000_000 + '"\n')
    with pytest.raises(ConfigError, match=r"huge\.toml is \d+ bytes: a config is at most 65536 bytes"):
        load_config(huge)


def test_invalid_utf8_names_the_file(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'[vehicle]\nurl = "udpin://caf\xe9:1"\n')
    with pytest.raises(ConfigError, match=r"latin1\.toml is not UTF-8 text \(byte 28"):
        load_config(path)
