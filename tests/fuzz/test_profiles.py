"""Profiles: any JSON document, damaged text, and the sample profile with a field removed or replaced by a
wrong type, NaN, a negative or huge number load, or raise a ProfileError naming the file and the field."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from softgrip_calib.profile import CalibrationProfile, ProfileError, load_profile, save_profile
from tests.fuzz.strategies import SAMPLE_PROFILE, json_values, mutated_profiles


def load_text(text: str) -> tuple[CalibrationProfile | None, str | None, str]:
    """Write ``text`` as a profile file and load it: (profile, None) or (None, error message), and the path."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gripper.json"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        try:
            return load_profile(path), None, str(path)
        except ProfileError as err:
            return None, str(err), str(path)


@settings(max_examples=100, deadline=None)
@given(json_values)
def test_any_json_document_is_refused_with_a_profile_error(document):
    profile, error, path = load_text(json.dumps(document))
    assert profile is None and error.startswith(f"{path}: ")


@settings(max_examples=60, deadline=None)
@given(st.text(max_size=40) | st.binary(max_size=40).map(lambda b: b.decode("latin-1")),
       st.integers(0, len(json.dumps(SAMPLE_PROFILE))))
def test_damaged_text_is_refused_with_a_profile_error(noise, at):
    text = json.dumps(SAMPLE_PROFILE)
    profile, error, path = load_text(text[:at] + noise)
    if profile is None:
        assert error.startswith(f"{path}: ")
    else:  # the noise only added whitespace, say
        assert profile.to_dict() == CalibrationProfile.from_dict(SAMPLE_PROFILE).to_dict()


@settings(max_examples=200, deadline=None)
@given(mutated_profiles())
def test_a_removed_or_wrong_field_loads_or_is_named(mutation):
    path, data = mutation
    profile, error, file = load_text(json.dumps(data))
    if profile is None:
        assert error.startswith(f"{file}: ")
        assert str(path[0]) in error  # the section: version, gripper, fingers, segmentation, camera, fit
        assert [k for k in path if isinstance(k, str)][-1] in error  # the field (or list) itself
    else:
        # Whatever loads can be saved and loads back the same (finite numbers, known fields).
        with tempfile.TemporaryDirectory() as tmp:
            saved = save_profile(profile, Path(tmp) / "again.json")
            assert load_profile(saved).to_dict() == profile.to_dict()
        numbers = [v for v in json_leaves(profile.to_dict()) if isinstance(v, float)]
        assert all(math.isfinite(v) for v in numbers)


def json_leaves(node):
    if isinstance(node, dict):
        for v in node.values():
            yield from json_leaves(v)
    elif isinstance(node, list):
        for v in node:
            yield from json_leaves(v)
    else:
        yield node
