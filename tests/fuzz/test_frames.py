"""Frames: random sizes, bit depths, channels, corrupt PNGs and bad intrinsics load or raise a FrameError
naming the input; arrays with NaN, inf and wrong dtypes are refused with a FrameError; a real frame
painted over becomes a scene or a FrameSceneError naming it."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.fuzz.strategies import frame_files, intrinsic_values
from softgrip_vision.frames import Frame, FrameError, Intrinsics, load_frame, save_frame

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
        # only these get through; float depth is metres, stored as uint16 units of depth_scale
        assert color.dtype == np.uint8 and (depth.dtype == np.uint16 or np.issubdtype(depth.dtype, np.floating))
        assert frame.depth.dtype == np.uint16 and frame.depth.shape == depth.shape
        check_loaded(frame)


@st.composite
def painted(draw, frame: Frame) -> Frame:
    """``frame`` with up to four rectangles painted over it: a random colour, and a random depth (0 = no
    reading, 65535 = far) or the depth left as it was."""
    color, depth = frame.color.copy(), frame.depth.copy()
    h, w = depth.shape
    for _ in range(draw(st.integers(1, 4))):
        x0, y0 = draw(st.integers(0, w - 1)), draw(st.integers(0, h - 1))
        x1, y1 = draw(st.integers(x0 + 1, w)), draw(st.integers(y0 + 1, h))
        color[y0:y1, x0:x1] = draw(st.tuples(*[st.integers(0, 255)] * 3))
        value = draw(st.one_of(st.none(), st.sampled_from([0, 1, 65535]), st.integers(0, 65535)))
        if value is not None:
            depth[y0:y1, x0:x1] = value
    if not depth.any():
        depth[0, 0] = 1
    return Frame(color=color, depth=depth, intrinsics=frame.intrinsics)


@settings(max_examples=15, deadline=None)  # 640 x 480 frames: about 0.3 s each
@given(st.data())
def test_a_painted_over_real_frame_becomes_a_scene_or_a_frame_scene_error_naming_it(data):
    # The command's pipeline up to the core's inputs (segmentation, keypoints, the object's SDF), without
    # compiling an estimate.
    from softgrip_calib.profile import load_profile
    from softgrip_cli._pipeline import FrameSceneError, frame_scene

    frame = data.draw(painted(load_frame(SAMPLE)))
    profile = load_profile(SAMPLE.parent / "sample_profile.json")
    with tempfile.TemporaryDirectory() as tmp:
        folder = save_frame(frame, Path(tmp) / "painted")
        try:
            scene = frame_scene(folder, profile)
        except FrameSceneError as err:
            assert str(err).startswith(f"{folder}: ")
        else:
            assert np.isfinite(scene.pose).all() and np.isfinite(scene.bases_mm).all()
