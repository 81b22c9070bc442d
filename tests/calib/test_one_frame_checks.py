"""One-frame calibration refuses frames it would measure wrong instead of writing a wrong profile."""

from __future__ import annotations

import warnings

import pytest

from benchmarks.vision_accuracy import INTRINSICS, N_LINKS, accuracy_scenes, variant_scenes
from softgrip_calib.one_frame import one_frame_from_frames
from softgrip_jax import SoftgripError
from synthetic.render import render


def test_a_body_thinner_than_the_fingers_is_refused_not_measured():
    """A gripper body (a 6 mm bar, thinner than the 8 mm fingers) joining the open fingers: the
    fingers' centrelines run along the bar, so L by eq. 5 would be a chord across a corner. The
    calibration must stop with an error that names the open frame's finger and the fix."""
    scene = [s for s in accuracy_scenes(8) if s.object_name is not None][0]
    opened, closed = variant_scenes(scene, "flat base, body in view")
    opened.palm_height_mm = closed.palm_height_mm = 6.0
    with warnings.catch_warnings(), pytest.raises(SoftgripError, match=r"open frame is not straight.*roi"):
        warnings.simplefilter("ignore")
        one_frame_from_frames(render(closed, INTRINSICS), render(opened, INTRINSICS), N_LINKS)
