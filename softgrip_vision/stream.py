"""A planner's per-frame loop with its two halves overlapped: frames -> scenes -> scores.

:func:`score_frames` runs :func:`softgrip_vision.scene.frame_scene` on each frame and
:meth:`Scene.score <softgrip_vision.scene.Scene.score>` on poses for it, like the plain loop::

    for frame in frames:
        scene = frame_scene(frame, profile)
        result = scene.score(poses)

but scores each scene on a worker thread while the next frame is loaded and measured. The two
halves use different parts of the machine (the measurement is numpy, OpenCV and scipy on the
calling thread; the score one compiled XLA program, which releases the interpreter), so a frame
costs about the longer of the two instead of their sum. The price is latency: a frame's result
comes out after the next frame has been measured. The results are the plain loop's, bit for bit
(the same programs on the same inputs).

Example (the sample frame twice; the first score compiles, seconds):
    >>> import numpy as np
    >>> from softgrip_calib.profile import load_profile
    >>> from softgrip_jax import Geometric
    >>> from softgrip_vision.samples import sample_data_dir
    >>> data = sample_data_dir()
    >>> around = lambda scene: scene.pose + np.array([[0.0, 0.0, 0.0], [-4.0, 0.0, 0.0]])
    >>> for scene, result in score_frames([data / "circle_open"] * 2, load_profile(data / "sample_profile.json"),
    ...                                   around, estimator=Geometric()):
    ...     print(scene.name, [round(float(v), 3) for v in result.score])
    circle_open [0.196, 0.194]
    circle_open [0.196, 0.194]
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Float

from softgrip_vision.frames import Frame
from softgrip_vision.scene import ProfileLike, Scene, frame_scene

if TYPE_CHECKING:
    from softgrip_jax import AbstractEstimator, Score, ScoreWeights, Uncertainty


class ScoredFrame(NamedTuple):
    """One frame's :class:`~softgrip_vision.scene.Scene` and the :class:`softgrip_jax.Score` (numpy
    leaves) of the poses scored for it."""

    scene: Scene
    score: Score


def score_frames(frames: Iterable[str | os.PathLike[str] | Frame], profile: ProfileLike,
                 poses: Float[ArrayLike, "*b 3"] | Callable[[Scene], Float[ArrayLike, "*b 3"]], *,
                 estimator: AbstractEstimator | None = None, weights: ScoreWeights | None = None,
                 uncertainty: Uncertainty | None = None, settings: Any = None,
                 warn: Callable[[str], None] | None = None) -> Iterator[ScoredFrame]:
    """Score poses for each frame, in order, overlapping each frame's scoring with the next one's
    measurement (module docstring).

    Args:
        frames: frame folders or :class:`~softgrip_vision.frames.Frame` s, any iterable (a list, or a
            generator reading a camera: it is advanced one frame ahead of the results).
        profile: the calibration profile, as for :func:`~softgrip_vision.scene.frame_scene`.
        poses: (3,) or (B, 3) poses (x mm, y mm, angle rad) scored for every frame, or a function
            of the frame's :class:`~softgrip_vision.scene.Scene` returning them (e.g. poses around
            ``scene.pose``); called on the calling thread.
        estimator: as for :meth:`Scene.score <softgrip_vision.scene.Scene.score>`.
        weights: as for :meth:`Scene.score <softgrip_vision.scene.Scene.score>`.
        uncertainty: as for :meth:`Scene.score <softgrip_vision.scene.Scene.score>`.
        settings: as for :func:`~softgrip_vision.scene.frame_scene`.
        warn: as for :func:`~softgrip_vision.scene.frame_scene`.

    Yields:
        A :class:`ScoredFrame` ``(scene, score)`` per frame, in the frames' order.

    Raises:
        FrameSceneError: a frame that cannot be measured (the message names it), after the
            results of the frames before it have been yielded. An error of the scoring (e.g. bad
            poses) is raised where that frame's result would be yielded.
    """
    choose = poses if callable(poses) else (lambda _scene: poses)

    def scored(scene: Scene, chosen: np.ndarray) -> Score:
        return scene.score(chosen, estimator=estimator, weights=weights, uncertainty=uncertainty)

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="softgrip-score")
    pending: tuple[Scene, Future[Score]] | None = None
    done: tuple[Scene, Future[Score]] | None
    try:
        for frame in frames:
            try:
                scene = frame_scene(frame, profile, settings=settings, warn=warn)
                chosen = np.asarray(choose(scene))
            except BaseException:
                if pending is not None:  # the previous frame's result first: nothing is lost
                    done, pending = pending, None
                    yield ScoredFrame(done[0], done[1].result())
                raise
            # This frame's score starts before the previous result is handed out, so it runs while
            # the caller works on that result too.
            done, pending = pending, (scene, pool.submit(scored, scene, chosen))
            if done is not None:
                yield ScoredFrame(done[0], done[1].result())
        if pending is not None:
            done, pending = pending, None
            yield ScoredFrame(done[0], done[1].result())
    finally:  # also when the caller stops early: the running score finishes, nothing is left behind
        pool.shutdown(wait=True, cancel_futures=True)
