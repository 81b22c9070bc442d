"""Frames: random sizes, bit depths, channels, corrupt PNGs and bad intrinsics load or raise a FrameError
naming the input; arrays with NaN, inf and wrong dtypes are refused with a FrameError."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.fuzz.strategies import frame_files, intrinsic_values
from vision.frames import Frame, FrameError, Intrinsics, load_frame

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "circle_open"
FIELDS = ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale")


def check_loaded(frame: Frame) -> None:
    """What every loaded frame guarantees."""
    h, w = frame.depth.shape
    assert frame.color.dtype == np.uint8 and frame.color.shape == (h, w, 3)
    assert frame.depth.dtype == np.uint16 and frame.depth.any()
    intr = frame.intrinsics
    assert (intr.width, intr.height) == (w, h)
    assert all(np.isfinite(getattr(intr, name)) for name in FIELDS)
    assert intr.fx > 0 and intr.fy > 0 and intr.depth_scale > 0


@settings(max_examples=150, deadline=None)
@given(frame_files())
def test_a_frame_folder_loads_or_raises_a_frame_error_naming_it(files):
    with tempfile.TemporaryDirectory() as tmp:
        folder = files.write(Path(tmp) / "frame")
        try:
            frame = load_frame(folder)
        except FrameError as err:
            assert str(folder) in str(err)
        else:
            check_loaded(frame)


@settings(max_examples=40, deadline=None)
@given(name=st.sampled_from(["color.png", "depth.png"]), cut=st.floats(0.0, 1.0), flips=st.lists(
    st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=4))
def test_a_damaged_real_frame_loads_or_raises_a_frame_error_naming_the_file(name, cut, flips):
    data = bytearray((SAMPLE / name).read_bytes())
    for where, value in flips:
        data[int(where * (len(data) - 1))] = value
    data = bytes(data[:max(0, int(cut * len(data)))]) if cut < 1.0 else bytes(data)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "frame"
        folder.mkdir()
        for other in ("color.png", "depth.png", "intrinsics.json"):
            (folder / other).write_bytes((SAMPLE / other).read_bytes())
        (folder / name).write_bytes(data)
        try:
            frame = load_frame(folder)
        except FrameError as err:
            assert str(folder / name) in str(err)
        else:
            check_loaded(frame)


@settings(max_examples=100, deadline=None)
@given(st.fixed_dictionaries({name: intrinsic_values for name in FIELDS}))
def test_intrinsics_are_built_or_refused_with_a_frame_error(values):
    try:
        intr = Intrinsics.from_dict(values, source="camera.json")
    except FrameError as err:
        assert str(err).startswith("camera.json: ")
    else:
        assert all(np.isfinite(getattr(intr, name)) for name in FIELDS)
        assert intr.width > 0 and intr.height > 0 and intr.fx > 0 and intr.fy > 0 and intr.depth_scale > 0


ARRAY_DTYPES = st.sampled_from([np.uint8, np.uint16, np.int16, np.int32, np.float32, np.float64, np.bool_])


@st.composite
def arrays(draw, height: int, width: int) -> np.ndarray:
    dtype = draw(ARRAY_DTYPES)
    shape = draw(st.sampled_from([(height, width), (height, width, 3), (height, width, 1), (height,), (width, height, 3)]))
    array = np.ones(shape, dtype)
    if np.issubdtype(dtype, np.floating):
        array.flat[:draw(st.integers(0, array.size))] = draw(st.sampled_from([np.nan, np.inf, -np.inf, 0.0]))
    return array


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.data())
def test_frames_from_arrays_with_nan_inf_and_wrong_dtypes_are_refused(height, width, data):
    color, depth = data.draw(arrays(height, width)), data.draw(arrays(height, width))
    intr = Intrinsics(width=width, height=height, fx=10.0, fy=10.0, ppx=1.0, ppy=1.0, depth_scale=0.001)
    try:
        frame = Frame(color=color, depth=depth, intrinsics=intr)
    except FrameError:
        pass
    else:
        assert color.dtype == np.uint8 and depth.dtype == np.uint16  # only these get through
        check_loaded(frame)
