"""The ``intrinsics.json`` layout as a pydantic model: what every field must be, said once.

:func:`validate` checks a parsed JSON object against :class:`IntrinsicsDocument` and turns
pydantic's first error into the message :meth:`softgrip_vision.frames.Intrinsics.from_dict` gives (the field,
what it must be, the value), e.g. ``fx must be a finite number, got nan``. Each field's
``description`` says what it expects, which is also what :func:`json_schema`
(``softgrip_base/schemas/intrinsics.schema.json``) tells other tools. Keys other than these fields are allowed
and ignored. What the types cannot say (how many coefficients a distortion model takes, no
coefficients without a model) is checked by :class:`softgrip_vision.frames.Intrinsics` after this.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails

#: pyrealsense2's names for the seven required fields, in this order in messages.
REQUIRED = ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale")
#: Lens distortion models (as :data:`softgrip_vision.frames.DISTORTION_MODELS`; a test keeps them equal).
MODELS = ("none", "brown_conrady", "inverse_brown_conrady", "rational_polynomial", "kannala_brandt4",
          "modified_brown_conrady")


def _pixels(what: str) -> FieldInfo:
    return Field(strict=True, gt=0, description=f"the image's {what} in pixels (an integer > 0)")


def _number(description: str, *, gt: float | None = None) -> FieldInfo:
    return Field(strict=True, allow_inf_nan=False, description=description, gt=gt)


class IntrinsicsDocument(BaseModel):
    """The colour camera's pinhole intrinsics and depth unit (pyrealsense2's names; README: "File formats")."""

    model_config = ConfigDict(extra="allow", strict=True, frozen=True,
                              title="softgrip-jax camera intrinsics (intrinsics.json)")
    width: Annotated[int, _pixels("width")]
    height: Annotated[int, _pixels("height")]
    fx: Annotated[float, _number("focal length along x in pixels (a finite number > 0)", gt=0)]
    fy: Annotated[float, _number("focal length along y in pixels (a finite number > 0)", gt=0)]
    ppx: Annotated[float, _number("principal point x in pixels, from the centre of the top-left pixel "
                                  "(a finite number)")]
    ppy: Annotated[float, _number("principal point y in pixels, from the centre of the top-left pixel "
                                  "(a finite number)")]
    depth_scale: Annotated[float, _number("metres per unit of the 16-bit depth image (a finite number > 0; "
                                          "RealSense D4xx: 0.001)", gt=0)]
    model: Literal[MODELS] = Field(default="none", description="the lens distortion model")  # type: ignore[valid-type]
    coeffs: list[Annotated[float, _number("a distortion coefficient (a finite number)")]] = Field(
        default=[], description="the distortion model's coefficients (4, 5 or 8 numbers; none without a model)")


def validate(data: Any) -> tuple[IntrinsicsDocument | None, str | None]:
    """(the document, None), or (None, the problem) for the first problem pydantic finds: all
    missing fields at once, else the first bad field as ``<field> must be ..., got <value>``."""
    if not isinstance(data, dict):
        return None, (f"expected a JSON object with keys {', '.join(REQUIRED)}, got {type(data).__name__}")
    data = {key: value.item() if isinstance(value, np.generic) else value for key, value in data.items()}
    try:
        return IntrinsicsDocument.model_validate(data), None
    except ValidationError as err:
        errors = err.errors(include_url=False)
    missing = [str(e["loc"][0]) for e in errors if e["type"] == "missing"]
    if missing:
        return None, (f"missing key(s) {', '.join(missing)}; intrinsics need {', '.join(REQUIRED)} "
                      f"(pyrealsense2 names)")
    return None, _describe(errors[0], data)


def json_schema() -> dict[str, Any]:
    """The JSON Schema of ``intrinsics.json`` (``softgrip_base/schemas/intrinsics.schema.json`` is this, written out)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **IntrinsicsDocument.model_json_schema()}


def _describe(error: ErrorDetails, data: dict[str, Any]) -> str:
    name = str(error["loc"][0])
    value, kind = data.get(name), error["type"]
    if name == "model":
        return f"model (lens distortion) must be one of {', '.join(MODELS)}, got {value!r}"
    if name == "coeffs":
        what = "finite" if kind == "finite_number" else "a list of numbers"
        return f"coeffs must be {what}, got {value!r}"
    if name in ("width", "height"):
        what = "a positive integer (pixels)" if kind == "greater_than" else "an integer"
    else:
        what = {"finite_number": "a finite number", "greater_than": "positive"}.get(kind, "a number")
    return f"{name} must be {what}, got {value!r}"
