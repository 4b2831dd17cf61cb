"""The Foxglove layout shipped in docs/foxglove/ names only topics (and fields) the recorder writes."""

import json
import re
from pathlib import Path

from runtime.log import recorder
from runtime.log.topics import TOPIC_DEPTH, TOPIC_GRAY

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove" / "cmnav-layout.json"
# Where a Foxglove panel config names a topic or a message path.
TOPIC_KEYS = ("topicPath", "imageTopic", "value")
PATH = re.compile(r"^(/[A-Za-z0-9_/]+)(?:\.([A-Za-z0-9_]+))?")


def _message_paths(node, found: list[str]) -> list[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key in TOPIC_KEYS and isinstance(value, str) and value.startswith("/"):
                found.append(value)
            else:
                _message_paths(value, found)
    elif isinstance(node, list):
        for item in node:
            _message_paths(item, found)
    return found


def _problems(layout: dict) -> list[str]:
    """Each message path of the layout whose topic the recorder does not write, or whose first
    field is not in that topic's JSON schema."""
    schemas = {topic: props for topic, (_, _, props) in recorder._SCHEMAS.items()}
    images = {TOPIC_DEPTH, TOPIC_GRAY}
    problems = []
    for path in _message_paths(layout["configById"], []):
        match = PATH.match(path)
        topic, field = match.group(1), match.group(2)
        if topic in images:
            continue
        if topic not in schemas:
            problems.append(f"{path}: topic {topic} is not written by runtime.log.recorder")
        elif field is not None and field not in schemas[topic]:
            problems.append(f"{path}: {topic} has no field {field!r} (fields: {sorted(schemas[topic])})")
    return problems


def _panels(layout_tree) -> list[str]:
    if isinstance(layout_tree, str):
        return [layout_tree]
    return _panels(layout_tree["first"]) + _panels(layout_tree["second"])


def test_layout_names_only_what_the_recorder_writes():
    layout = json.loads(LAYOUT.read_text())
    paths = _message_paths(layout["configById"], [])
    topics = {PATH.match(p).group(1) for p in paths}
    # It shows what the issue asks for: both camera images, trajectory, command and velocity, watchdog.
    assert {"/camera/gray", "/camera/depth", "/vehicle/state", "/vehicle/command", "/watchdog"} <= topics
    assert _problems(layout) == []
    # Every panel configured is placed in the mosaic, and every placed panel is configured.
    assert sorted(_panels(layout["layout"])) == sorted(layout["configById"])


def test_the_check_finds_an_unknown_topic_and_field():
    layout = {"configById": {"Plot!a": {"paths": [{"value": "/vehicle/stat.pos_enu_m[0]"}, {"value": "/vehicle/state.pos_ned_m[0]"}]},
                             "Table!b": {"topicPath": "/watchdog"}}}  # fmt: skip
    problems = _problems(layout)
    assert len(problems) == 2
    assert "/vehicle/stat is not written" in problems[0] and "no field 'pos_ned_m'" in problems[1]
