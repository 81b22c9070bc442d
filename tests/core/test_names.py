"""Integer codes read back by name: softgrip_jax._names.code_names and the results' *_name properties."""

from __future__ import annotations

import numpy as np
import pytest

from softgrip_jax import CASE_NAMES, ContactCase, RefineStatus, Status
from softgrip_jax._names import code_names
from softgrip_vision.documents import status_name


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
