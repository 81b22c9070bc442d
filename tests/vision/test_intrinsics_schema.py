"""intrinsics.json validated by a pydantic model (softgrip_vision.intrinsics_schema), its JSON Schema on disk."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from softgrip_vision.frames import DISTORTION_MODELS, FrameError, Intrinsics
from softgrip_vision.intrinsics_schema import MODELS, json_schema

ROOT = Path(__file__).resolve().parents[2]
GOOD = {"width": 640, "height": 480, "fx": 385.0, "fy": 385, "ppx": 320.0, "ppy": 240.0, "depth_scale": 0.0001}


def test_the_intrinsics_schema_file_is_the_model_and_an_independent_validator_agrees():
    """softgrip_base/schemas/intrinsics.schema.json is what softgrip_vision.intrinsics_schema says (regenerate it with
    ``json_schema()`` after a change), and jsonschema, a validator independent of pydantic, accepts
    the sample frames' intrinsics and refuses what Intrinsics.from_dict refuses."""
    jsonschema = pytest.importorskip("jsonschema")
    on_disk = json.loads((ROOT / "softgrip_base" / "schemas" / "intrinsics.schema.json").read_text())
    assert on_disk == json_schema()
    validator = jsonschema.Draft202012Validator(on_disk)
    samples = sorted(ROOT.glob("data/*/intrinsics.json"))
    assert samples
    for path in samples:
        validator.validate(json.loads(path.read_text()))
    distorted = Intrinsics.from_dict({**GOOD, "model": "brown_conrady", "coeffs": [0.1, -0.2, 0.0, 0.0, 0.05]})
    validator.validate(distorted.to_dict())
    validator.validate({**GOOD, "serial": "123"})  # other keys are ignored
    for key, value in [("fx", 0), ("fy", -1.0), ("width", 30.5), ("height", 0), ("ppx", "320"), ("depth_scale", None),
                       ("width", True), ("model", "magic"), ("coeffs", ["x"]), ("ppy", None)]:
        data = {**GOOD, key: value}
        assert not validator.is_valid(data), (key, value)
        with pytest.raises(FrameError, match=f"camera.json: {key} (\\(lens distortion\\) )?must be"):
            Intrinsics.from_dict(data, source="camera.json")
    missing = {k: v for k, v in GOOD.items() if k != "ppy"}
    assert not validator.is_valid(missing)
    with pytest.raises(FrameError, match=r"camera.json: missing key\(s\) ppy; intrinsics need width"):
        Intrinsics.from_dict(missing, source="camera.json")


def test_the_schema_names_every_distortion_model_and_describes_every_field():
    assert MODELS == tuple(DISTORTION_MODELS)
    properties = json_schema()["properties"]
    assert properties["model"]["enum"] == list(DISTORTION_MODELS)
    assert all(properties[name].get("description") for name in properties)
    assert json_schema()["required"] == ["width", "height", "fx", "fy", "ppx", "ppy", "depth_scale"]


def test_numpy_numbers_are_accepted_as_before():
    intr = Intrinsics.from_dict({**GOOD, "width": np.int64(640), "fx": np.float32(385.0), "ppx": np.int32(320)})
    assert intr == Intrinsics.from_dict(GOOD)
    assert type(intr.width) is int and type(intr.fx) is float
    with pytest.raises(FrameError, match="ppy must be a number, got True"):
        Intrinsics.from_dict({**GOOD, "ppy": np.bool_(True)})
