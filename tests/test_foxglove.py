"""The Foxglove messages of a real run's logs against Foxglove's published JSON schemas (tests/data/foxglove)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from agent.runtime import foxglove
from mission_log.reader import read_log

jsonschema = pytest.importorskip("jsonschema")
SCHEMAS = Path(__file__).parent / "data" / "foxglove"


def published(name: str) -> dict:
    return json.loads((SCHEMAS / f"{name}.json").read_text())


def assert_same_fields(message, schema: dict, where: str = "") -> None:
    """Every object carries exactly the fields the schema lists: the published schemas require none, and
    Foxglove reads a missing field as absent, so validation alone would pass a message missing half of them."""
    if schema.get("type") == "object" and "properties" in schema:
        assert isinstance(message, dict), where
        assert set(message) == set(schema["properties"]), f"{where}: {sorted(set(message) ^ set(schema['properties']))}"
        for name, sub in schema["properties"].items():
            assert_same_fields(message[name], sub, f"{where}.{name}")
    elif schema.get("type") == "array" and "items" in schema:
        for n, item in enumerate(message):
            assert_same_fields(item, schema["items"], f"{where}[{n}]")


def foxglove_messages(path: Path, schema_title: str) -> list[dict]:
    log = read_log(path)
    return [m for topic, messages in log.topics.items() for _, m in messages
            if topic.endswith("/tf" if schema_title == "foxglove.FrameTransforms" else "/scene")]


@pytest.mark.parametrize("name", ["FrameTransforms", "SceneUpdate"])
def test_logged_foxglove_messages_match_the_published_schemas(fleet_run, name):
    folder, _ = fleet_run
    schema = published(name)
    validator = jsonschema.Draft7Validator(schema)
    checked = 0
    for path in sorted(folder.glob("*.mcap")):
        messages = foxglove_messages(path, schema["title"])
        assert messages, f"{path.name} has no {name}"
        for message in messages:
            errors = sorted(validator.iter_errors(message), key=str)
            assert not errors, f"{path.name}: {errors[0].message}"
            assert_same_fields(message, schema)
            checked += 1
    # Three agents and the bridge: transforms every tick (121), the scene once a second (13).
    assert checked == 4 * (121 if name == "FrameTransforms" else 13)


def test_the_channels_carry_the_schema_names_foxglove_knows(fleet_run):
    from mcap.reader import make_reader

    folder, _ = fleet_run
    with (folder / "agent-1.mcap").open("rb") as handle:
        summary = make_reader(handle).get_summary()
    names = {summary.channels[c].topic: summary.schemas[summary.channels[c].schema_id].name for c in summary.channels}
    assert names["/1/tf"] == "foxglove.FrameTransforms" and names["/1/scene"] == "foxglove.SceneUpdate"


def test_the_estimate_frames_place_neighbours_and_target_where_the_estimates_say(fleet_run):
    # p_ij = p_i - p_j: the frame of i's estimate of j is at -p^_ij from vessel i, the target's at -p^_io.
    folder, _ = fleet_run
    log = read_log(folder / "agent-3.mcap")
    estimates = dict(log.messages("/3/estimates"))
    t, frames = log.messages("/3/tf")[-1]
    by_child = {f["child_frame_id"]: f for f in frames["transforms"]}
    estimate = estimates[t]
    for j, neighbour in estimate["neighbours"].items():
        moved = by_child[foxglove.estimate_frame("3", j)]
        assert moved["parent_frame_id"] == "vessel/3"
        assert (moved["translation"]["x"], moved["translation"]["y"]) == (-neighbour["position"][0],
                                                                          -neighbour["position"][1])
    target = by_child["vessel/3/estimate/target"]["translation"]
    assert (target["x"], target["y"]) == (-estimate["target_state"][0], -estimate["target_state"][1])
    assert frames["transforms"][0]["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}


def test_the_transforms_written_directly_are_what_the_model_dumps():
    written = foxglove.transforms(12_345_678_901, [("vessel/1", "vessel/1/hull", 1.5, -2.0, 0.3),
                                                   ("world", "target", 0.0, 4.0, 0.0)])
    assert foxglove.FrameTransforms.model_validate(written).model_dump() == written


def test_a_static_scene_restamped_is_what_the_models_dump_at_that_stamp():
    scene = foxglove.StaticScene([*foxglove.target_entities(0, "target", 5.0, "target"),
                                  *foxglove.island_entities(0, "world", [[(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]])])
    for stamp in (3_000_000_000, 4_250_000_001):
        built = foxglove.SceneUpdate(entities=[*foxglove.target_entities(stamp, "target", 5.0, "target"),
                                               *foxglove.island_entities(stamp, "world",
                                                                          [[(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]])])
        assert scene.at(stamp) == built.model_dump(mode="json")


def test_a_heading_becomes_a_rotation_about_z():
    turned = foxglove.yaw_rotation(math.pi / 2)
    assert (turned.x, turned.y) == (0.0, 0.0)
    assert turned.z == pytest.approx(math.sqrt(0.5)) and turned.w == pytest.approx(math.sqrt(0.5))
