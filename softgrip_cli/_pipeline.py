"""What the commands share, split by what it does; the names here stay for existing callers.

- frame -> scene: :mod:`softgrip_vision.scene` (public: ``frame_scene``, ``Scene``, ``FrameSceneError``),
  plus :func:`load_profile`, :func:`gripper_from_profile` and :func:`segmentation_settings` below;
- scene -> results: ``Scene.estimate`` and ``Scene.score`` (:mod:`softgrip_vision.scene`), and
  :func:`estimate_scene` below;
- results -> files: JSON documents in :mod:`softgrip_vision.documents`, pictures in
  :mod:`softgrip_cli._pictures` (OpenCV overlays) and :mod:`softgrip_vision.plots` (matplotlib), output
  files and folders in :mod:`softgrip_cli._files`.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from softgrip_base.input_guard import one_line
from softgrip_cli._files import add_force_argument, check_output_file, ensure_dir, frame_inputs, unique_png_names
from softgrip_cli._pictures import caption, grasp_overlay
from softgrip_vision.documents import (SIDES, candidate_json, components_json, failed_frame_json, finger_contacts_mm,
                              finger_json, fingers_json, frame_json, number_json, points_json, pose_json,
                              status_name)
from softgrip_vision.scene import (OPEN_BEND_WARN, SEPARATION_WARN_MM, FrameScene, FrameSceneError, Scene, pose_from_bases,
                          take, to_numpy, with_lengths)

__all__ = [
    "OPEN_BEND_WARN", "SEPARATION_WARN_MM", "SIDES", "FrameScene", "FrameSceneError", "Scene", "add_force_argument",
    "candidate_json", "caption", "check_output_file", "components_json", "configure_output",
    "enable_compilation_cache",
    "ensure_dir", "estimate_grasp_jit", "info", "note", "estimate_scene", "failed_frame_json", "finger_contacts_mm",
    "finger_json", "fingers_json", "frame_inputs", "frame_json", "frame_scene", "gripper_from_profile",
    "grasp_overlay", "load_profile", "number_json", "points_json", "pose_from_bases", "pose_json",
    "quiet", "segmentation_settings", "status_name", "take", "to_numpy", "unique_png_names", "warn",
]


def enable_compilation_cache() -> None:
    """Keep JAX's compiled programs on disk (``softgrip_jax.enable_compilation_cache`` with its default
    folder), so that the second run of a command starts in seconds. ``SOFTGRIP_JAX_CACHE=0`` turns it
    off. A cache folder that other users can write is refused with a warning (the cache is then off)."""
    from softgrip_jax import enable_compilation_cache as enable

    enable()


#: The commands' diagnostics on stderr (stdout is reserved for results): :func:`warn`, :func:`note`
#: and :func:`info` log at WARNING, INFO and DEBUG; ``-q`` / ``-v`` set its level
#: (:func:`configure_output`).
LOG = logging.getLogger("softgrip_cli")


class _StderrHandler(logging.Handler):
    """Writes each record to the ``sys.stderr`` of the moment (a stream redirected or captured after
    the handler was made is honoured), warnings as ``warning: ...``, each line escaped by
    :func:`softgrip_base.input_guard.one_line` (a file name's ESC, newline or invalid UTF-8 bytes
    never reach the terminal raw)."""

    def emit(self, record: logging.LogRecord) -> None:
        prefix = "warning: " if record.levelno >= logging.WARNING else ""
        print(prefix + one_line(record.getMessage()), file=sys.stderr)


def configure_output(quiet: bool = False, verbose: bool = False) -> None:
    """``-q``: nothing on stderr but errors; ``-v``: details too; neither: warnings and summaries.
    ``-q`` wins over ``-v``. Called once per command; replaces this logger's handler."""
    LOG.setLevel(logging.ERROR if quiet else logging.DEBUG if verbose else logging.INFO)
    LOG.propagate = False  # a caller's own logging set-up does not print these twice
    for handler in [h for h in LOG.handlers if isinstance(h, _StderrHandler)]:
        LOG.removeHandler(handler)
    LOG.addHandler(_StderrHandler())


configure_output()  # warnings and summaries, until a command sets -q / -v


def quiet() -> bool:
    """Whether summaries (and progress bars) are silenced (``-q``)."""
    return not LOG.isEnabledFor(logging.INFO)


def note(message: str) -> None:
    """A summary line on stderr (how many, how long); silent with ``-q``."""
    LOG.info(one_line(message))  # escaped here too: other handlers (a caller's, pytest's) get it


def info(message: str) -> None:
    """A detail on stderr, printed with ``-v`` only."""
    LOG.debug(one_line(message))  # escaped here too: other handlers (a caller's, pytest's) get it


def warn(message: str) -> None:
    """One diagnostic line on stderr (stdout is reserved for results); silent with ``-q``."""
    LOG.warning(one_line(message))  # escaped here too: other handlers (a caller's, pytest's) get it


# ---------------------------------------------------------------------------------------------
# Profiles


def load_profile(path: str | os.PathLike[str]):
    """The calibration profile at ``path`` (``softgrip_calib.profile.load_profile``; errors name the file),
    with its path as ``source``, so that a frame that does not match it names the file
    (:func:`softgrip_vision.plausibility.check_profile_match`)."""
    from softgrip_calib.profile import load_profile as _load

    profile = _load(path)
    object.__setattr__(profile, "source", str(path))  # not a field: to_dict and equality ignore it
    return profile


def gripper_from_profile(profile, lengths_mm: tuple[float, float] | None = None):
    """The core's ``Gripper`` of a profile, with each finger's length replaced by ``lengths_mm``
    (left, right) when given."""
    return with_lengths(profile.gripper(), lengths_mm)


def segmentation_settings(profile):
    """The profile's :class:`~softgrip_vision.segmentation.SegmentationSettings`."""
    from softgrip_vision.segmentation import SegmentationSettings

    return SegmentationSettings.from_dict(profile.segmentation, source="the profile's segmentation")


# ---------------------------------------------------------------------------------------------
# Frame -> scene -> results


def frame_scene(path, profile, *, length_from_frame: bool = False, settings=None) -> Scene:
    """:func:`softgrip_vision.scene.frame_scene` with the profile's segmentation settings read as the
    commands read them, and warnings printed on stderr."""
    from softgrip_vision.scene import frame_scene as _frame_scene

    settings = segmentation_settings(profile) if settings is None else settings
    return _frame_scene(path, profile, length_from_frame=length_from_frame, settings=settings, warn=warn)


def estimate_grasp_jit():
    """``softgrip_jax.estimate_grasp`` compiled once (per frame size and N) for the whole process."""
    from softgrip_vision.scene import _estimate_grasp_jit

    return _estimate_grasp_jit()


def estimate_scene(scene: Scene, estimator=None):
    """Both fingers' estimates at the frame's own pose, as numpy (a ``GraspEstimate``), with the
    deformation ``estimator`` (``softgrip_jax.Geometric()`` or ``Mechanics(config)``; None: the default)."""
    return scene.estimate(estimator=estimator)
