from __future__ import annotations

import copy
import enum
import json
from pathlib import Path

import numpy as np
import pytest

from mergesvc import errors
from mergesvc.core.model import (
    MatchResult,
    ObjectArrays,
    ObjectMap,
    RejectReason,
    Submap,
    arrays_to_nodes,
    json_schemas,
    parse_model,
)
from mergesvc.wire.files import load_model

D = 8


def _doc(n: int = 3) -> dict:
    rng = np.random.default_rng(0)
    return {
        "schema_version": 1,
        "robot_id": "auv1",
        "session_id": "s0",
        "objects": [
            {
                "id": f"o{k}",
                "position": rng.normal(size=3).tolist(),
                "embedding": rng.normal(size=D).tolist(),
                "variance": 0.1 if k % 2 else rng.uniform(0.1, 1, size=D).tolist(),
                "n_obs": k + 1,
            }
            for k in range(n)
        ],
    }


def test_valid_file_and_uncertainty() -> None:
    doc = _doc()
    m = parse_model(ObjectMap, json.dumps(doc))
    arr = m.arrays()
    assert arr.n == 3 and arr.dim == D
    np.testing.assert_allclose(arr.variances_nd[1], 0.1)  # scalar = isotropic
    np.testing.assert_allclose(arr.uncertainty_s[1], 0.1)
    np.testing.assert_allclose(arr.uncertainty_s[0], np.mean(doc["objects"][0]["variance"]))
    sub = parse_model(Submap, json.dumps({**doc, "seq": 4, "stamp": 12.5}))
    assert sub.seq == 4


def test_arrays_round_trip() -> None:
    m = parse_model(ObjectMap, json.dumps(_doc()))
    arr = m.arrays()
    back = ObjectArrays.from_objects(arrays_to_nodes(arr))
    for name in ("position_xyz_m", "embeddings_nd", "variances_nd", "n_obs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(arr, name))
    assert isinstance(arrays_to_nodes(arr)[1].variance, float)


def test_a_copy_with_other_objects_has_their_arrays() -> None:
    """model_copy(update=...) used to carry the original's cached arrays over: a submap copied
    with 60 objects matched as the 8 it was copied from."""
    sub = parse_model(Submap, json.dumps({**_doc(3), "seq": 0}))
    assert sub.arrays().n == 3
    more = sub.model_copy(update={"objects": [*sub.objects, sub.objects[0].model_copy(
        update={"id": "o9"})]})
    assert more.arrays().n == 4 and more.arrays().ids[-1] == "o9"
    up = sub.model_copy(update={"up": (0.0, 0.0, 1.0)})
    np.testing.assert_array_equal(up.arrays().up_xyz, [0.0, 0.0, 1.0])
    same = sub.model_copy()
    assert same.arrays() is sub.arrays()  # nothing changed: the arrays are shared
    # pickled (a child process's job): the arrays alone, the same values, no cache
    import pickle

    arr = sub.arrays()
    arr.cache["x"] = object()
    back = pickle.loads(pickle.dumps(arr))
    assert back.cache == {} and back.ids == list(arr.ids)
    for name in ("position_xyz_m", "embeddings_nd", "variances_nd", "n_obs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(arr, name))


def _mutate(path: list, value) -> dict:
    doc = copy.deepcopy(_doc())
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return doc


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        (_mutate(["schema_version"], 2), "schema_version"),
        (_mutate(["objects", 1, "embedding", 2], float("nan")), "objects.1.embedding.2"),
        (_mutate(["objects", 1, "position", 0], float("inf")), "objects.1.position.0"),
        (_mutate(["objects", 1, "variance"], -1.0), "objects.1.variance"),
        (_mutate(["objects", 0, "variance"], [0.1] * (D - 1)), "objects.0"),
        (_mutate(["objects", 1, "embedding"], [0.0] * (D + 1)), "objects.1"),
        (_mutate(["objects", 2, "id"], "o0"), "duplicate id"),
        (_mutate(["objects"], []), "objects"),
        (_mutate(["objects", 0, "n_obs"], 0), "objects.0.n_obs"),
        (_mutate(["objects", 0, "colour"], "red"), "objects.0.colour"),
        (_mutate(["objects", 0, "embedding"], [0.0] * 5000), "objects.0.embedding"),
        (_mutate(["robot_id"], ""), "robot_id"),
    ],
)
def test_bad_input_names_the_field(doc: dict, field: str) -> None:
    with pytest.raises(errors.SchemaError) as info:
        parse_model(ObjectMap, json.dumps(doc))
    msg = str(info.value)
    assert field in msg
    assert "\n" not in msg


def test_malformed_json_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(errors.DecodeError):
        parse_model(ObjectMap, b"{not json")
    with pytest.raises(errors.SchemaError):
        parse_model(ObjectMap, b"[1, 2]")
    with pytest.raises(errors.DecodeError):
        load_model(ObjectMap, tmp_path / "missing.json")


def test_match_result_covariance_shape() -> None:
    ok = dict(accepted=False, reason=RejectReason.TOO_FEW_MATCHES, matches=[], transform=None,
              covariance=None, timings_ms={"total": 1.0})
    assert set(MatchResult(**ok).cli_dict()) == {
        "accepted", "reason", "matches", "transform", "covariance", "timings_ms"}
    with pytest.raises(ValueError, match="6x6"):
        MatchResult(**{**ok, "covariance": [[0.0] * 5] * 6})


def test_schema_files_match_models() -> None:
    """schemas/ is generated from the models; regenerate with `mergesvc schemas`."""
    folder = Path(__file__).resolve().parents[1] / "schemas"
    for name, schema in json_schemas().items():
        text = json.dumps(schema, indent=2, sort_keys=True) + "\n"
        assert (folder / name).read_text() == text, f"{name} drifted: run `mergesvc schemas`"


def test_error_tree_exports() -> None:
    for name in errors.__all__:
        obj = getattr(errors, name)
        if name == "TransportFault":  # the one vocabulary of the tree: why a session failed
            assert issubclass(obj, enum.Enum)
            continue
        # beside the tree, the two helpers that word its messages
        assert issubclass(obj, errors.MergeError) if isinstance(obj, type) else name in (
            "one_line", "cannot_read")
    assert issubclass(errors.DecodeError, errors.InputError)
    assert issubclass(errors.SchemaError, errors.InputError)
