"""schemas/ with an off-the-shelf JSON Schema 2020-12 validator (jsonschema): every file
mergesvc writes validates, and what the CLI refuses the schema refuses too, where JSON Schema
can say it (issue 15). What it cannot say is listed in mergesvc.core.model.json_schemas."""

from __future__ import annotations

import copy
import json
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import run_cli
from jsonschema import Draft202012Validator

from mergesvc.core.model import Factor, MatchResult, ObjectMap, Submap, json_schemas
from mergesvc.core.pipeline import match
from mergesvc.errors import SchemaError
from mergesvc.fleet.replies import RelocalizeReply, SubmapResult, reply_schemas
from mergesvc.sim import Family, make_scenario
from mergesvc.wire.files import load_model

SCHEMAS = Path(__file__).resolve().parents[1] / "schemas"
GOLDEN = Path(__file__).resolve().parent / "golden"
DIALECT = "https://json-schema.org/draft/2020-12/schema"


def validator(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((SCHEMAS / name).read_text()))


def errors(name: str, doc: Any) -> list[str]:
    return [e.message for e in validator(name).iter_errors(doc)]


@pytest.fixture(scope="module")
def example() -> dict[str, Any]:
    """What `mergesvc example OUT --family underwater --seed 4` writes, and `match --json`."""
    sc = make_scenario(Family.UNDERWATER, seed=4)
    result = match(sc.map, sc.submap).result
    return {
        "map": json.loads(sc.map.model_dump_json()),
        "submap": json.loads(sc.submap.model_dump_json()),
        "truth": json.loads(json.dumps(sc.truth_dict())),
        "result": json.loads(json.dumps(result.cli_dict())),
        "result_model": json.loads(result.model_dump_json()),
    }


def test_every_schema_is_a_2020_12_schema_with_an_id() -> None:
    files = sorted(p.name for p in SCHEMAS.glob("*.schema.json"))
    # the files and messages (core), and what the service sends as JSON (fleet/replies.py)
    assert files == sorted(json_schemas() | reply_schemas())
    assert {"submap_result.schema.json", "status_reply.schema.json",
            "relocalize_reply.schema.json"} <= set(files)
    ids = set()
    for name in files:
        schema = json.loads((SCHEMAS / name).read_text())
        assert schema["$schema"] == DIALECT
        Draft202012Validator.check_schema(schema)
        ids.add(schema["$id"])
    assert len(ids) == len(files)


def test_schema_version_is_a_constant() -> None:
    for name in ("object_map", "submap", "factor", "error_message", "match_result",
                 "submap_result", "status_reply", "relocalize_reply"):
        schema = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
        assert schema["properties"]["schema_version"]["const"] == 1, name


def test_the_files_mergesvc_writes_validate(example: dict[str, Any]) -> None:
    assert errors("object_map.schema.json", example["map"]) == []
    assert errors("submap.schema.json", example["submap"]) == []
    assert errors("truth.schema.json", example["truth"]) == []
    assert errors("match_result.schema.json", example["result"]) == []
    assert errors("match_result.schema.json", example["result_model"]) == []


def test_the_kitti_example_and_its_truth_validate() -> None:
    sc = make_scenario(Family.KITTI, seed=2)
    assert errors("object_map.schema.json", json.loads(sc.map.model_dump_json())) == []
    assert errors("submap.schema.json", json.loads(sc.submap.model_dump_json())) == []
    assert errors("truth.schema.json", json.loads(json.dumps(sc.truth_dict()))) == []


@pytest.mark.parametrize("path", sorted(GOLDEN.glob("*.json")), ids=lambda p: p.stem)
def test_every_golden_message_validates(path: Path) -> None:
    """NAME.json's decoded document, and NAME.in.json's document as the sender had it."""
    if path.name == "index.json":
        return
    doc = json.loads(path.read_text())
    if path.name.endswith(".in.json"):
        kind, message = doc["type"], doc["document"]
    else:
        kind, message = doc["envelope"]["type"], doc["message"]
    schema = {"submap": "submap", "map": "object_map", "factor": "factor",
              "error": "error_message"}[kind]
    assert errors(f"{schema}.schema.json", message) == []


Edit = Callable[[dict], None]


def _set(path: str, value: Any) -> Edit:
    def edit(doc: dict) -> None:
        *parents, last = path.split(".")
        node: Any = doc
        for k in parents:
            node = node[int(k)] if isinstance(node, list) else node[k]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return edit


def _delete(path: str) -> Edit:
    def edit(doc: dict) -> None:
        *parents, last = path.split(".")
        node: Any = doc
        for k in parents:
            node = node[int(k)] if isinstance(node, list) else node[k]
        del node[last]
    return edit


ODOMETRY = {
    "from_keyframe": 0,
    "T_from_to": {"translation": [1.0, 0.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
    "covariance": [[0.01 if i == j else 0.0 for j in range(6)] for i in range(6)],
}
# files `mergesvc match` refuses and the schema can refuse too
REFUSED: dict[str, Edit] = {
    "schema_version 2": _set("schema_version", 2),
    "schema_version as text": _set("schema_version", "1"),
    "an unknown field": _set("colour", "red"),
    "no objects": _set("objects", []),
    "no robot_id": _delete("robot_id"),
    "an empty object id": _set("objects.0.id", ""),
    "an id of 129 characters": _set("objects.0.id", "x" * 129),
    "n_obs 0": _set("objects.0.n_obs", 0),
    "n_obs 1.5": _set("objects.0.n_obs", 1.5),
    "a variance of 0": _set("objects.0.variance", 0.0),
    "a negative per-dimension variance": _set("objects.0.variance", [-1.0] * 4),
    "a position of 2 numbers": _set("objects.0.position", [1.0, 2.0]),
    "an empty embedding": _set("objects.0.embedding", []),
    "a label of 129 characters": _set("objects.0.label", "x" * 129),
    "up the zero vector": _set("up", [0.0, 0.0, -0.0]),
    "a negative seq": _set("seq", -1),
    "odometry without keyframe": _set("odometry", ODOMETRY),
    "an odometry covariance of 5 rows": lambda d: d.update(
        keyframe=3, odometry={**ODOMETRY, "covariance": ODOMETRY["covariance"][:5]}),
    "an odometry covariance row of 7": lambda d: d.update(keyframe=3, odometry={
        **ODOMETRY, "covariance": [[*row, 0.0] for row in ODOMETRY["covariance"]]}),
}
# files `mergesvc match` refuses that JSON Schema cannot express (checked by the models)
NOT_EXPRESSIBLE: dict[str, Edit] = {
    "a per-dimension variance of the wrong length": _set("objects.0.variance", [0.1, 0.2]),
    "embeddings of two lengths": lambda d: d["objects"][1]["embedding"].append(0.5),
    "a duplicate object id": lambda d: d["objects"][1].update(id=d["objects"][0]["id"]),
    "odometry from a later keyframe": lambda d: d.update(
        keyframe=3, odometry={**ODOMETRY, "from_keyframe": 5}),
    "an odometry quaternion of norm 2": lambda d: d.update(keyframe=3, odometry={
        **ODOMETRY, "T_from_to": {"translation": [0, 0, 0], "quaternion_wxyz": [2, 0, 0, 0]}}),
}


def _write(tmp_path: Path, doc: dict) -> Path:
    path = tmp_path / "submap.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_the_schema_refuses_what_the_cli_refuses(case: str, example: dict[str, Any],
                                                 tmp_path: Path) -> None:
    doc = copy.deepcopy(example["submap"])
    REFUSED[case](doc)
    with pytest.raises(SchemaError):
        load_model(Submap, _write(tmp_path, doc))  # what `match --submap` reads it with
    assert errors("submap.schema.json", doc), f"the schema accepts {case}"


@pytest.mark.parametrize("case", sorted(NOT_EXPRESSIBLE))
def test_what_json_schema_cannot_say_the_models_still_refuse(
    case: str, example: dict[str, Any], tmp_path: Path
) -> None:
    """Documents the gap: these pass the schema, and `match` refuses them."""
    doc = copy.deepcopy(example["submap"])
    NOT_EXPRESSIBLE[case](doc)
    with pytest.raises(SchemaError):
        load_model(Submap, _write(tmp_path, doc))
    assert errors("submap.schema.json", doc) == []


def test_the_models_refuse_numbers_as_text_as_the_schema_does(
    example: dict[str, Any], tmp_path: Path
) -> None:
    """An object's numbers written as text ("1.5") are refused by the models and the schema
    alike (they were coerced once: pydantic's lax mode)."""
    doc = copy.deepcopy(example["submap"])
    doc["objects"][0]["position"] = ["1", "2", "3"]
    with pytest.raises(SchemaError, match=r"objects\.0\.position\.0: Input should be a valid"):
        load_model(Submap, _write(tmp_path, doc))
    assert errors("submap.schema.json", doc)


@pytest.mark.parametrize(("edit", "line"), [
    # a union (one number or a list) refusing a value: the field's path, counted once
    (lambda d: d["objects"][0].update(variance=0.0),
     r"objects\.0\.variance: Input should be greater than 0$"),
    (lambda d: d["objects"][0].update(embedding=d["objects"][0]["embedding"][:7]),
     r"embeddings differ in length: objects\.0 \(\S+\) has 7 values, objects\.1 \(\S+\) has "),
    (lambda d: d["objects"][1].update(n_obs=2**64),
     r"objects\.1\.n_obs: a number too large"),
    (lambda d: d["objects"][0].update({"size-m": 1.0}),  # a field of the user's own naming
     r"objects\.0\.size-m: Extra inputs are not permitted$"),
])
def test_a_refused_file_names_the_field_a_user_wrote(
    example: dict[str, Any], tmp_path: Path, edit: Callable[[dict], None], line: str
) -> None:
    doc = copy.deepcopy(example["map"])
    edit(doc)
    with pytest.raises(SchemaError, match=line):
        load_model(ObjectMap, _write(tmp_path, doc))


def test_a_map_of_schema_version_2_is_refused_by_the_cli_and_the_schema(
    example: dict[str, Any], tmp_path: Path
) -> None:
    doc = {**example["map"], "schema_version": 2}
    path = tmp_path / "map.json"
    path.write_text(json.dumps(doc))
    sub = tmp_path / "sub.json"
    sub.write_text(json.dumps(example["submap"]))
    r = run_cli("match", "--map", str(path), "--submap", str(sub))  # in-process
    assert r.returncode == 2 and "schema_version" in r.stderr
    assert errors("object_map.schema.json", doc)


def test_the_factor_schema_refuses_half_a_keyframe_pair() -> None:
    doc = json.loads((GOLDEN / "factor_full_keyframes.json").read_text())["message"]
    assert errors("factor.schema.json", doc) == []
    for drop in ("keyframe_a", "keyframe_b"):
        half = {k: v for k, v in doc.items() if k != drop}
        with pytest.raises(ValueError, match="together"):
            Factor.model_validate(half)
        assert errors("factor.schema.json", half)
        assert errors("factor.schema.json", {**doc, drop: None})
    bad = {**doc, "covariance": doc["covariance"][:5]}
    with pytest.raises(ValueError):
        Factor.model_validate(bad)
    assert errors("factor.schema.json", bad)


def test_the_truth_schema_refuses_malformed_truth(example: dict[str, Any]) -> None:
    truth = example["truth"]
    for bad in (
        {k: v for k, v in truth.items() if k != "transform"},
        {**truth, "extra": 1},
        {**truth, "matches": {"s0": 3}},
        {**truth, "equivalent": {"s0": ["m1"]}},
        {**truth, "transform": {"translation": [0, 0], "quaternion_wxyz": [1, 0, 0, 0]}},
    ):
        assert errors("truth.schema.json", bad)


def test_match_results_validate_and_their_schema_refuses_a_bad_covariance(
    example: dict[str, Any],
) -> None:
    result = example["result"]
    assert result["covariance"] is not None
    bad = {**result, "covariance": result["covariance"][:5]}
    with pytest.raises(ValueError):
        MatchResult.model_validate(bad)
    assert errors("match_result.schema.json", bad)
    assert errors("object_map.schema.json", {**example["map"], "objects": "none"})
    ObjectMap.model_validate(example["map"])  # the map itself is fine


def test_the_schemas_written_are_the_ones_the_build_makes(tmp_path: Path) -> None:
    """`mergesvc schemas --check` on the repository's schemas/ passes; on a folder missing the
    service's reply schemas it fails."""

    def check(folder: Path) -> subprocess.CompletedProcess:
        return run_cli("schemas", str(folder), "--check")  # in-process

    assert check(SCHEMAS).returncode == 0
    for name in json_schemas():
        (tmp_path / name).write_text((SCHEMAS / name).read_text())
    r = check(tmp_path)
    assert r.returncode != 0 and "status_reply.schema.json" in r.stderr


def test_the_reply_schemas_refuse_what_the_models_refuse() -> None:
    ok = json.loads(SubmapResult(robot="auv1", session="s0", seq=3, outcome="no_match",
                                 reason="ambiguous").model_dump_json())
    assert errors("submap_result.schema.json", ok) == []
    for bad in ({**ok, "outcome": "lost"}, {**ok, "reason": "bad_luck"}, {**ok, "seq": -1},
                {**ok, "schema_version": 2}, {**ok, "extra": 1}, {**ok, "code": "nope"}):
        with pytest.raises(ValueError):
            SubmapResult.model_validate(bad)
        assert errors("submap_result.schema.json", bad), bad
    reloc = {"schema_version": 1, "localized": True, "reason": "verified", "anchor": "a/s0",
             "T_anchor_session": {"translation": [1, 2, 3], "quaternion_wxyz": [1, 0, 0, 0]},
             "covariance": (np.eye(6) * 0.1).tolist(), "matches": 5, "keyframe": None}
    assert errors("relocalize_reply.schema.json", reloc) == []
    bad = {**reloc, "covariance": reloc["covariance"][:5]}
    with pytest.raises(ValueError):
        RelocalizeReply.model_validate(bad)
    assert errors("relocalize_reply.schema.json", bad)
