"""``load_config(path)``: the TOML file of ``cmnav fly`` -> :class:`runtime.config.RuntimeConfig`.

Each TOML table is one dataclass of ``runtime.config`` (``[policy]`` -> ``PolicyModelConfig``,
``[policy.limits]`` -> ``runtime.contract.ActionLimits``, ...) and each key one of its fields, so
the defaults stay in the dataclasses.  Everything is checked before anything talks to the
vehicle: an unknown key, a value of the wrong type, a value out of range, limits looser than the
contract, a missing model file or a model whose SHA-256 differs all raise :class:`ConfigError`
with the dotted key and what is allowed.  Relative paths are relative to the config file's folder.
"""

from __future__ import annotations

import dataclasses
import difflib
import sys
import types
import typing
from pathlib import Path
from typing import Any

from .config import ConfigError, RuntimeConfig
from .contract import LimitError
from .service.paths import directory_problem

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6): the same parser as a package
    import tomli as tomllib

__all__ = ["ConfigError", "load_config"]


# A config is a page of settings: anything this large (or nested this deep) is not one.
CONFIG_MAX_BYTES = 64 * 1024
CONFIG_MAX_DEPTH = 8


def load_config(path: str | Path) -> RuntimeConfig:
    """Read, type-check and validate the config at ``path``, and check the files it names.
    Every :class:`ConfigError` names the file and, for a value, the dotted key."""
    path = Path(path)
    try:
        return _load(path)
    except ConfigError as err:
        message = str(err)
        raise ConfigError(message if message.startswith(str(path)) else f"{path}: {message}") from err


def _load(path: Path) -> RuntimeConfig:
    try:
        size = path.stat().st_size
        if size > CONFIG_MAX_BYTES:
            raise ConfigError(f"{path} is {size} bytes: a config is at most {CONFIG_MAX_BYTES} bytes (is it the right file?)")
        text = path.read_bytes().decode("utf-8")
    except OSError as err:
        raise ConfigError(f"cannot read config file {path}: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path} is not UTF-8 text (byte {err.start}: {err.reason}): save it as UTF-8") from err
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path} is not valid TOML: {err}") from err
    except RecursionError as err:
        raise ConfigError(f"{path} nests arrays or tables too deeply to parse: a config has at most {CONFIG_MAX_DEPTH} levels") from err
    if (depth := _depth(data)) > CONFIG_MAX_DEPTH:
        raise ConfigError(f"{path} nests {depth} levels of arrays or tables: a config has at most {CONFIG_MAX_DEPTH}")
    config = _build(RuntimeConfig, data, "")
    if config.mission.goal_source == "config" and config.mission.goal_rel_home_enu_m is None:
        raise ConfigError("mission.goal_rel_home_enu_m is missing: set [mission] goal_rel_home_enu_m = [east, north, up] (m from home), "
                          'or goal_source = "mission" to fly the waypoints uploaded to the autopilot')
    config = _resolve_paths(config, path.resolve().parent)
    _check_files(config)
    return config


def _depth(value: Any) -> int:
    if isinstance(value, dict):
        return 1 + max((_depth(v) for v in value.values()), default=0)
    if isinstance(value, list):
        return 1 + max((_depth(v) for v in value), default=0)
    return 0


# ---------------------------------------------------------------------- TOML -> dataclasses


def _build(cls: type, table: Any, prefix: str) -> Any:
    """Instantiate dataclass ``cls`` from a TOML table whose keys are under ``prefix``."""
    where = prefix.rstrip(".") or "the top level"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table ([{where}]), got {_toml_type(table)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key in table:
        if key not in fields:
            close = difflib.get_close_matches(key, list(fields), n=1)
            hint = f"; did you mean {prefix}{close[0]}?" if close else ""
            raise ConfigError(f"unknown key {prefix}{key} in {where} (allowed: {', '.join(fields)}){hint}")
    kwargs = {key: _convert(hints[key], value, f"{prefix}{key}") for key, value in table.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except LimitError as err:  # its message starts with the field name
        raise ConfigError(f"{prefix}{err}: a deployment may clamp tighter than the contract, never looser") from err
    except ValueError as err:  # range checks of dataclasses outside runtime.config name their key already
        raise ConfigError(str(err)) from err


def _convert(hint: Any, value: Any, key: str) -> Any:
    """``value`` from TOML as type ``hint``; :class:`ConfigError` naming ``key`` if it is not one."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # "X | None": TOML has no null, so a value is an X
        (hint,) = [a for a in args if a is not type(None)]
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, f"{key}.")
    if origin is tuple:
        if not isinstance(value, list):
            raise _type_error(key, value, _describe(hint))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key} = {value!r} has {len(value)} values: must be {_describe(hint)}")
        return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
        Path: isinstance(value, str) and value != "",
    }
    if hint not in ok:
        raise TypeError(f"{key}: the config loader cannot map the type {hint!r}")  # a dataclass field type it lacks
    if not ok[hint]:
        raise _type_error(key, value, _describe(hint))
    return float(value) if hint is float else Path(value) if hint is Path else value


def _describe(hint: Any) -> str:
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0]).removeprefix('a ').removeprefix('an ')}s"
        return f"a list of {len(args)} {_describe(args[0]).removeprefix('a ').removeprefix('an ')}s"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string", Path: "a path (non-empty string)"}[hint]


def _type_error(key: str, value: Any, expected: str) -> ConfigError:
    return ConfigError(f"{key} = {value!r} is {_toml_type(value)}: must be {expected}")


def _toml_type(value: Any) -> str:
    names = {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "a list", dict: "a table"}
    return names.get(type(value), f"a {type(value).__name__}")


# ---------------------------------------------------------------------- paths and files


def _resolve_paths(config: RuntimeConfig, base: Path) -> RuntimeConfig:
    """Paths relative to the config file's folder ``base`` -> absolute."""

    def absolute(p: Path | None) -> Path | None:
        return None if p is None else (p if p.is_absolute() else base / p)

    return dataclasses.replace(
        config,
        policy=dataclasses.replace(
            config.policy,
            model_path=absolute(config.policy.model_path),
            tensorrt=dataclasses.replace(config.policy.tensorrt, engine_cache_dir=absolute(config.policy.tensorrt.engine_cache_dir)),
        ),
        recorder=dataclasses.replace(config.recorder, log_dir=absolute(config.recorder.log_dir)),
        camera=dataclasses.replace(
            config.camera,
            replay=dataclasses.replace(config.camera.replay, path=absolute(config.camera.replay.path)),
            bag=dataclasses.replace(config.camera.bag, path=absolute(config.camera.bag.path)),
        ),
    )


def _check_files(config: RuntimeConfig) -> None:
    """The files and names the config refers to exist (before anything talks to the vehicle)."""
    import onnxruntime as ort  # the flight runtime loads it anyway; keep `import runtime.config_loader` light

    from .model import file_sha256

    policy = config.policy
    if not policy.model_path.is_file():
        raise ConfigError(f"policy.model_path = {str(policy.model_path)!r}: no such file (export one with `cmnav export`)")
    if not policy.model_file.is_file():
        raise ConfigError(f"policy.variant = {policy.variant!r}: no {policy.model_file} next to policy.model_path "
                          f"(export it with `cmnav export ... --variants {policy.variant}`, or fly \"fp32\")")  # fmt: skip
    if policy.model_sha256 is not None:
        actual = file_sha256(policy.model_file)
        if actual != policy.model_sha256.lower():
            raise ConfigError(
                f"policy.model_sha256 = {policy.model_sha256!r} but {policy.model_file} has SHA-256 {actual}: "
                "the model file is not the one the config names (copy the right file, or update the hash)"
            )
    known = ort.get_all_providers()
    unknown = [p for p in policy.providers if p not in known]
    if unknown:
        raise ConfigError(f"policy.providers: unknown execution provider(s) {unknown} (ONNX Runtime knows: {', '.join(known)})")
    replay = config.camera.replay.path
    if config.camera.source == "replay" and replay is not None and not replay.is_file():
        raise ConfigError(f"camera.replay.path = {str(replay)!r}: no such file")
    bag = config.camera.bag.path
    if config.camera.source == "bag" and bag is not None and not bag.is_file():
        raise ConfigError(f"camera.bag.path = {str(bag)!r}: no such file (a recording from realsense-viewer or rs.recorder)")
    log_dir = config.recorder.log_dir
    if log_dir is not None and (problem := directory_problem(log_dir)) is not None:
        raise ConfigError(f"recorder.log_dir = {str(log_dir)!r}: {problem} (chown it to the service user, or choose another)")
