"""Hypothesis strategies for the fuzz tests: JSON documents, frame folders on disk, bad field values."""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from hypothesis import strategies as st

#: Any JSON document (NaN and infinities included: Python's json reads and writes them).
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12,
)

#: Values a field should not have: wrong types, non-finite, negative, zero, huge, far too precise.
bad_values = st.one_of(
    st.sampled_from([None, True, False, "", "abc", [], {}, [1.0], {"a": 1}, math.nan, math.inf, -math.inf, 0, 0.0,
                     -1, -1.0, 1e-300, 1e300, 10**40, -(10**40), 0.5, 3]),
    st.integers(), st.floats(), st.text(max_size=5), json_values,
)

#: Numbers for the seven intrinsics fields, the bad ones included.
intrinsic_values = st.one_of(st.floats(), st.integers(-5, 64), st.sampled_from([0, 0.0, -1.0, math.nan, math.inf]),
                             bad_values)


@dataclass
class FrameFiles:
    """The three files of a frame folder as bytes (None: the file is missing)."""

    color: bytes | None
    depth: bytes | None
    intrinsics: bytes | None

    def write(self, folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in (("color.png", self.color), ("depth.png", self.depth), ("intrinsics.json", self.intrinsics)):
            if data is not None:
                (folder / name).write_bytes(data)
        return folder


def _png(image: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".png", image)
    assert ok
    return buffer.tobytes()


@st.composite
def images(draw, height: int, width: int) -> np.ndarray:
    """A PNG-encodable image of the given size: 8 or 16 bits, 1, 3 or 4 channels, random content
    (all zeros sometimes)."""
    dtype = draw(st.sampled_from([np.uint8, np.uint16]))
    channels = draw(st.sampled_from([1, 3, 4]))
    shape = (height, width) if channels == 1 else (height, width, channels)
    fill = draw(st.sampled_from(["random", "zeros", "max"]))
    if fill == "zeros":
        return np.zeros(shape, dtype)
    if fill == "max":
        return np.full(shape, np.iinfo(dtype).max, dtype)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    return rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)


@st.composite
def corrupted(draw, data: bytes) -> bytes | None:
    """``data`` unchanged, truncated, with bytes overwritten, replaced by noise, emptied, or missing (None)."""
    how = draw(st.sampled_from(["intact", "intact", "truncate", "overwrite", "noise", "empty", "missing"]))
    if how == "truncate":
        return data[:draw(st.integers(0, max(0, len(data) - 1)))]
    if how == "overwrite":
        at = draw(st.integers(0, max(0, len(data) - 1)))
        patch = draw(st.binary(min_size=1, max_size=8))
        return data[:at] + patch + data[at + len(patch):]
    if how == "noise":
        return draw(st.binary(max_size=64))
    if how == "empty":
        return b""
    if how == "missing":
        return None
    return data


def _good_intrinsics(height: int, width: int) -> dict:
    return {"width": width, "height": height, "fx": 20.0, "fy": 20.0, "ppx": width / 2, "ppy": height / 2,
            "depth_scale": 0.001}


@st.composite
def bad_intrinsics_json(draw, height: int, width: int) -> bytes:
    """intrinsics.json with wrong values (any field, the size too) or missing keys, any JSON document,
    or damaged bytes."""
    data = _good_intrinsics(height, width)
    kind = draw(st.sampled_from(["fields", "fields", "missing", "document", "bytes"]))
    if kind == "document":
        return json.dumps(draw(json_values)).encode()
    if kind == "fields":
        for key in draw(st.sets(st.sampled_from(sorted(data)), min_size=1, max_size=3)):
            data[key] = draw(intrinsic_values)
    elif kind == "missing":
        for key in draw(st.sets(st.sampled_from(sorted(data)), min_size=1, max_size=7)):
            del data[key]
    text = json.dumps(data).encode()
    return draw(corrupted(text)) if kind == "bytes" else text


@st.composite
def frame_files(draw, max_side: int = 12) -> FrameFiles:
    """A frame folder's files: a random size, and one part broken (or none): the colour or depth image
    (a random bit depth and channel count, all zeros, damaged or missing bytes), the intrinsics (bad
    values, missing keys, not an object, damaged), or the depth image's size."""
    height, width = draw(st.integers(1, max_side)), draw(st.integers(1, max_side))
    broken = draw(st.sampled_from(["nothing", "nothing", "color", "depth", "intrinsics", "size"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    color = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    depth = rng.integers(1, 65536, (height, width), dtype=np.uint16)
    if broken == "size":
        depth = rng.integers(1, 65536, (draw(st.integers(1, max_side)), draw(st.integers(1, max_side))),
                             dtype=np.uint16)
    color_png, depth_png = _png(color), _png(depth)
    if broken == "color":
        color_png = draw(corrupted(_png(draw(images(height, width)))))
    if broken == "depth":
        depth_png = draw(corrupted(_png(draw(images(height, width)))))
    intrinsics = json.dumps(_good_intrinsics(height, width)).encode()
    if broken == "intrinsics":
        intrinsics = draw(bad_intrinsics_json(height, width))
    return FrameFiles(color=color_png, depth=depth_png, intrinsics=intrinsics)


#: The sample profile shipped in data/, as a JSON object.
SAMPLE_PROFILE = json.loads((Path(__file__).resolve().parents[2] / "data" / "sample_profile.json").read_text())


def _paths(node, prefix=()):
    """Every key path of a JSON document, parents before children."""
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in children:
        yield prefix + (key,)
        yield from _paths(child, prefix + (key,))


@st.composite
def mutated_profiles(draw) -> tuple[tuple, dict]:
    """(path, profile): the sample profile with the field at ``path`` (a tuple of keys and indices)
    removed or replaced by one of ``bad_values``."""
    path = draw(st.sampled_from(list(_paths(SAMPLE_PROFILE))))
    data = copy.deepcopy(SAMPLE_PROFILE)
    parent = data
    for key in path[:-1]:
        parent = parent[key]
    if draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(bad_values)
    return path, data
