"""Integer codes read back by name: softgrip_jax._names.code_names and the results' *_name properties."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from softgrip_jax import CASE_NAMES, ContactCase, RefineStatus, Status
from softgrip_jax._names import code_names
from softgrip_vision.documents import finger_json, status_name
from softgrip_vision.frames import Intrinsics
from softgrip_vision.geometry import PlaneCamera


def test_every_code_reads_as_its_members_lower_case_name_in_the_shape_it_came():
    assert [code_names(int(c), ContactCase) for c in ContactCase] == list(CASE_NAMES)
    grid = np.array([[0, 2], [4, 9]])
    names = code_names(grid, Status)
    assert names.shape == (2, 2) and names.tolist() == [["ok", "base_outside_sdf"],
                                                          ["root_not_converged", "non_finite_result"]]
    assert code_names(np.int32(1), RefineStatus) == "no_improvement"


def test_a_code_the_enum_does_not_have_is_named_unknown_not_guessed():
    assert code_names(7, ContactCase) == "unknown(7)"
    assert code_names(np.array([-1, 0]), ContactCase).tolist() == ["unknown(-1)", "none"]


@pytest.mark.parametrize("status", list(Status))
def test_status_names_are_those_the_json_documents_write(status):
    assert code_names(int(status), Status) == status_name(int(status))


def test_a_status_code_status_does_not_have_is_status_n_in_the_document_and_unknown_n_from_code_names():
    # One implementation, two spellings of an unknown code: the JSON documents keep "status_<code>".
    assert code_names(42, Status) == "unknown(42)"
    assert code_names(np.array([42, 0]), Status).tolist() == ["unknown(42)", "ok"]
    assert status_name(42) == "status_42" and status_name(np.int32(-3)) == "status_-3"
    assert status_name(42, penetrating=True) == "status_42"  # only a usable (ok) estimate reads "penetrating"
    assert status_name(0, penetrating=True) == "penetrating"
    # A finger's entry of the document, as `softgrip estimate --json` writes it.
    camera = PlaneCamera(Intrinsics(width=64, height=48, fx=50.0, fy=50.0, ppx=32.0, ppy=24.0, depth_scale=1e-3),
                         depth_mm=120.0)
    estimate = SimpleNamespace(joints=np.zeros((3, 2)), status=np.int32(42), case=np.int32(ContactCase.NONE),
                               valid=np.bool_(False), event=np.bool_(False), sensitivity=np.float32(0.0))
    entry = json.loads(json.dumps(finger_json("left", estimate, SimpleNamespace(theta_entire=0.5), camera)))
    assert entry["status"] == "status_42" and entry["case"] == "none" and entry["contacts_mm"] == []
