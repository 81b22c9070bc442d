"""The calibration profile's JSON layout as pydantic models: what every field must be, said once.

:func:`validate` checks a parsed JSON object against :class:`ProfileDocument` and turns pydantic's
first error into one line that names the field as a path and says what it expects, e.g.
``fingers.left.theta_entire: expected a number in [0, pi/2), got "abc"``. Each leaf field carries
that expectation in its ``description`` (:func:`number`, :func:`text`), which is also what
:func:`json_schema` (``softgrip_base/schemas/profile.schema.json``) tells other tools. What a field's type cannot
say (the format version, one value per frame, the free-closure pair among the frames) is checked
in :mod:`softgrip_calib.profile` after this.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal, get_args

from pydantic import (BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError, ValidatorFunctionWrapHandler,
                      WrapValidator)
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails, PydanticCustomError

#: Largest magnitude of a number in a profile: the core computes in float32 (max 3.4e38).
MAX_MAGNITUDE = 1e30
#: Largest finger length and base separation (mm) and half-thickness (mm) of a profile: a gripper
#: up to a metre (softgrip_vision.plausibility measures fingers up to 1 m in a frame). Beyond that a value is
#: a unit mistake (metres typed as micrometres) or a corrupted file, refused when it is loaded.
MAX_SIZE_MM = 1000.0
MAX_HALF_THICKNESS_MM = 250.0
#: Most links a finger may have: the paper uses N <= 20, and memory grows with N^2 per candidate
#: in the mechanics estimate.
MAX_N_LINKS = 100


def _expecting(expected: str, magnitude: bool = False) -> WrapValidator:
    """Any error of the wrapped value becomes one that says ``expected`` (and, for numbers beyond
    :data:`MAX_MAGNITUDE`, that limit)."""
    def wrap(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            out = handler(value)
        except ValidationError:
            raise PydanticCustomError("expected", "{expected}", {"expected": expected}) from None
        if magnitude and abs(out) > MAX_MAGNITUDE:
            raise PydanticCustomError("expected", "{expected}",
                                      {"expected": f"{expected}, at most {MAX_MAGNITUDE:g} in magnitude"})
        return out
    return WrapValidator(wrap)


def number(expected: str, *, gt: float | None = None, ge: float | None = None, lt: float | None = None,
           le: float | None = None) -> tuple[FieldInfo, WrapValidator]:
    """A finite JSON number (not a boolean) within the bounds (pydantic's gt, ge, lt, le): the
    metadata of ``Annotated[float, *number(...)]``."""
    return (Field(strict=True, allow_inf_nan=False, description=expected, gt=gt, ge=ge, lt=lt, le=le),
            _expecting(expected, magnitude=True))


def text(choices: Any = None) -> tuple[FieldInfo, WrapValidator]:
    """A non-empty string (``Annotated[str, *text()]``), or one of the values of the ``Literal``
    type ``choices`` (``Annotated[choices, *text(choices)]``)."""
    if choices is None:
        return Field(strict=True, min_length=1, description="a non-empty string"), _expecting("a non-empty string")
    expected = "one of " + ", ".join(f'"{c}"' for c in get_args(choices))
    return Field(description=expected), _expecting(expected)


_Text = Annotated[str, *text()]
_FitMethod = Literal["one-frame", "least-squares"]
_EstimateMethod = Literal["geometric", "mechanics"]
_PlaneDepthUsed = Literal["open"]
_NonNegative = Annotated[float, *number("a number >= 0", ge=0)]
#: A standard error: one number, or one per component of a vector parameter (base_offset).
_StandardError = Annotated[
    Annotated[_NonNegative, Tag("number")] | Annotated[list[_NonNegative], Tag("list")],
    Discriminator(lambda v: "list" if isinstance(v, list) else "number"),
]
_UNION_TAGS = ("number", "list")


class _Object(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class Gripper(_Object):
    base_separation: Annotated[float, *number(f"a distance in mm > 0 and <= {MAX_SIZE_MM:g}", gt=0, le=MAX_SIZE_MM)]


class Finger(_Object):
    length: Annotated[float, *number(f"a length in mm > 0 and <= {MAX_SIZE_MM:g}", gt=0, le=MAX_SIZE_MM)]
    theta_entire: Annotated[float, *number("a number in [0, pi/2)", ge=0, lt=math.pi / 2)]
    half_thickness: Annotated[float, *number(f"a half-thickness in mm >= 0 and <= {MAX_HALF_THICKNESS_MM:g}",
                                             ge=0, le=MAX_HALF_THICKNESS_MM)]
    n_links: Annotated[int, Field(strict=True, ge=1, le=MAX_N_LINKS),
                       _expecting(f"an integer >= 1 and <= {MAX_N_LINKS}")]
    base_offset: Annotated[list[Annotated[float, *number("a finite number of mm")]],
                           Field(min_length=2, max_length=2, description="[dx, dy] in mm (two numbers)")] = [0.0, 0.0]
    stiffness_ratio: Annotated[float, *number("a base-to-tip stiffness ratio > 0 (1: uniform)", gt=0)] = 1.0
    base_compliance: Annotated[float, *number("a base compliance >= 0 (0: clamped base)", ge=0)] = 0.0


class Fingers(_Object):
    left: Finger
    right: Finger


class Camera(_Object):
    name: _Text
    # Checked field by field by softgrip_vision.frames.Intrinsics.from_dict.
    intrinsics: dict[str, Any] | None = Field(description="the camera's intrinsics (a JSON object) or null")


class Skipped(_Object):
    frame: _Text
    reason: _Text


class Candidate(_Object):
    """One stiffness model a fit tried (softgrip_calib.select)."""

    model: _Text
    parameters: list[_Text]
    residual_rms_mm: _NonNegative | None = None
    held_out_rms_mm: _NonNegative | None = None
    failure: _Text | None = None


class ModelSelection(_Object):
    chosen: _Text
    reason: _Text
    candidates: list[Candidate]


class Fit(_Object):
    method: Annotated[_FitMethod, *text(_FitMethod)]
    estimate_method: Annotated[_EstimateMethod, *text(_EstimateMethod)] | None = None
    frames: list[_Text]
    residual_rms_mm: _NonNegative | None = None
    frame_residual_rms_mm: list[_NonNegative] = []
    frame_start_residual_rms_mm: list[_NonNegative] = []
    frame_mid_error_mm: list[_NonNegative] = []
    frame_tip_error_mm: list[_NonNegative] = []
    standard_errors: dict[str, _StandardError] = Field(
        default={}, description="a JSON object (parameter name -> standard error)")
    skipped: list[Skipped] = []
    free_closure: _Text | None = None
    model_selection: ModelSelection | None = None


class PlaneDepths(_Object):
    """The gripper plane's depth measured in each frame of a one-frame calibration (a record)."""

    open: Annotated[float, *number("the plane's depth in mm in the open frame (> 0)", gt=0)]
    closed: Annotated[float, *number("the plane's depth in mm in the closed frame (> 0)", gt=0)]
    used: Annotated[_PlaneDepthUsed, *text(_PlaneDepthUsed)]


class Vision(BaseModel):
    """How the fingers are measured (softgrip_vision.measure.MeasureSettings checks those fields) and what
    calibration detected."""

    model_config = ConfigDict(extra="allow", strict=True, frozen=True)
    detected: dict[str, Any] = Field(default={}, description="a JSON object (what calibration detected)")
    plane_depth_mm: PlaneDepths | None = None


class ProfileDocument(_Object):
    """A calibration profile file (README: "File formats")."""

    version: Annotated[int, Field(strict=True, description="the format version"), _expecting("1")]
    gripper: Gripper
    fingers: Fingers
    # Checked field by field by softgrip_vision.segmentation.SegmentationSettings.from_dict.
    segmentation: dict[str, Any] = Field(
        description="a JSON object of segmentation settings ({} for the defaults)")
    camera: Camera
    vision: Vision = Vision()
    fit: Fit


def validate(data: Any) -> tuple[ProfileDocument | None, str | None]:
    """(the document, None), or (None, ``"path: problem"``) for the first problem pydantic finds."""
    try:
        return ProfileDocument.model_validate(data), None
    except ValidationError as err:
        return None, _describe(err.errors(include_url=False)[0])


def json_schema() -> dict[str, Any]:
    """The profile's JSON Schema (``softgrip_base/schemas/profile.schema.json`` is this, written out)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **ProfileDocument.model_json_schema(),
            "title": "softgrip-jax calibration profile"}


def _describe(error: ErrorDetails) -> str:
    """One pydantic error as ``path: problem``."""
    loc = list(error["loc"])
    if loc[:2] == ["fit", "standard_errors"] and len(loc) > 3 and loc[3] in _UNION_TAGS:
        del loc[3]  # which member of the number-or-list union pydantic tried: not part of the path
    path = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in loc).lstrip(".")
    kind, value = error["type"], error.get("input")
    if kind == "missing":
        return f"{path}: expected a value (the field is missing)"
    if kind == "extra_forbidden":
        return f"{path}: unknown field (valid: {', '.join(_field_names(loc[:-1]))})"
    if kind == "expected":
        expected = error["ctx"]["expected"]
    elif kind == "list_type":
        expected = "a JSON array"
    else:  # a JSON object expected, or a list of the wrong length: the field's own description
        expected = _description(loc) or "a JSON object"
    return f"{path}: expected {expected}, got {show_value(value)}"


def _model_at(loc) -> type[BaseModel] | None:
    """The model class whose fields the object at ``loc`` holds, or None."""
    model: Any = ProfileDocument
    for part in loc:
        if not (isinstance(model, type) and issubclass(model, BaseModel)) or part not in model.model_fields:
            return None
        model = model.model_fields[part].annotation
    return model if isinstance(model, type) and issubclass(model, BaseModel) else None


def _field_names(loc) -> list[str]:
    model = _model_at(loc)
    return list(model.model_fields) if model is not None else []


def _description(loc) -> str | None:
    model = _model_at(loc[:-1])
    if model is None or loc[-1] not in model.model_fields:
        return None
    return model.model_fields[loc[-1]].description


def show_value(value: Any) -> str:
    """A value as JSON text (strings quoted), shortened."""
    try:
        shown = json.dumps(value)
    except (TypeError, ValueError):
        shown = repr(value)
    return shown if len(shown) <= 60 else shown[:57] + "..."
