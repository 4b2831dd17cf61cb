"""Defaults live in the config dataclasses only: every `cmnav` option that sets a config field
defaults to None (the dataclass keeps the one value) and `--help` shows the dataclass's default;
no other option of a command repeats a default of the configs it builds."""

from __future__ import annotations

import argparse
import dataclasses
import importlib

import pytest

from cmnav.cli import _ConfigDefaultsFormatter, _config_option, _field_default, _shown, build_parser


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, subparser in action.choices.items():
                yield from _parsers(subparser, (*path, name))


def _config(spec: str) -> type:
    module, _, cls = spec.partition(":")
    return getattr(importlib.import_module(module), cls)


def repeated_defaults(parser: argparse.ArgumentParser) -> list[str]:
    """Options of ``parser`` whose own default equals the same-named field's of a config it sets."""
    configs = {field.rpartition(".")[0] for action in parser._actions for field in getattr(action, "config_fields", ())}
    problems = []
    for action in parser._actions:
        if getattr(action, "config_fields", ()) or not action.option_strings or action.default in (None, argparse.SUPPRESS):
            continue
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            continue  # a flag's False is no setting
        for spec in sorted(configs):
            for field in dataclasses.fields(_config(spec)):
                has_default = field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING
                if field.name == action.dest and has_default and _field_default(f"{spec}.{field.name}") == action.default:
                    problems.append(f"{parser.prog} {action.option_strings[0]} repeats {spec}.{field.name}'s default")
    return problems


PARSERS = list(_parsers(build_parser()))


@pytest.mark.parametrize("path, parser", PARSERS, ids=[" ".join(path) or "cmnav" for path, _ in PARSERS])
def test_config_options_default_to_none_and_help_shows_the_dataclass_default(path, parser):
    formatter = parser._get_formatter()
    assert isinstance(formatter, _ConfigDefaultsFormatter)
    for action in parser._actions:
        fields = getattr(action, "config_fields", ())
        if not fields:
            continue
        assert action.default is None, (path, action.option_strings)
        text = formatter._get_help_string(action)
        for field in fields:
            assert _shown(_field_default(field)) in text, (path, action.option_strings, text)
    assert repeated_defaults(parser) == []


def test_the_training_commands_take_their_defaults_from_the_configs():
    configured = {(" ".join(path), action.option_strings[0]) for path, parser in PARSERS for action in parser._actions
                  if getattr(action, "config_fields", ())}  # fmt: skip
    assert {("train cmwae", "--batch-size"), ("train policy", "--rollout"), ("eval policy", "--levels"),
            ("pipeline", "--teacher-envs"), ("dataset", "--frames-per-room")} <= configured  # fmt: skip


def test_help_prints_the_dataclass_default(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "cmwae", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--batch-size BATCH_SIZE pairs per optimizer step (default 64)" in help_text and "lambda of the MMD term (default 10.0)" in help_text


def test_a_given_option_reaches_the_config_and_an_omitted_one_keeps_its_default():
    from cmnav.cli import _given

    args = build_parser().parse_args(["eval", "policy", "--policy", "P", "--episodes", "7"])
    assert args.levels is None and _given(args, "episodes", "levels", "seed") == {"episodes": 7}


def test_the_check_finds_a_planted_repeated_default():
    parser = argparse.ArgumentParser(prog="planted", formatter_class=_ConfigDefaultsFormatter)
    _config_option(parser, "--episodes", "training.policy.evaluate:PolicyEvalConfig.episodes", type=int, help="episodes")
    parser.add_argument("--seed", type=int, default=0)  # PolicyEvalConfig.seed is 0 too
    assert repeated_defaults(parser) == ["planted --seed repeats training.policy.evaluate:PolicyEvalConfig.seed's default"]


@pytest.mark.parametrize("path, parser", PARSERS, ids=[" ".join(path) or "cmnav" for path, _ in PARSERS])
def test_help_prints_percent_signs_once(path, parser):
    """argparse %-formats an option's help but prints a description as written: a `%%` meant for
    the one shows doubled in the other."""
    assert "%%" not in parser.format_help(), path
