"""The sample frames that ship with the package: where they are.

Synthetic RGB-D frames (640x480, a D405 looking at the gripper plane 120 mm away) of a calibration
pair (``calib_open``, ``calib_closed``) and three scenes (``circle``, ``square``, ``star_a``, each
``<name>_open`` and ``<name>_closed``), plus ``sample_profile.json``, the profile they were drawn with.
``softgrip demo``, the README's examples and the docstring examples read them.

In an installed wheel they are package data (``softgrip_vision/sample_data/``); in a source
checkout (an editable install included) they are the repository's ``data/``, the one copy, which
the wheel's build maps into the package.

Example:
    >>> from softgrip_vision.samples import sample_data_dir
    >>> data = sample_data_dir()
    >>> sorted(p.name for p in data.glob("*_open"))
    ['calib_open', 'circle_open', 'square_open', 'star_a_open']
    >>> (data / "sample_profile.json").is_file()
    True
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["sample_data_dir"]


def sample_data_dir() -> Path:
    """The folder of the sample frames (frame folders ``<name>_open``/``<name>_closed`` and
    ``sample_profile.json``): ``softgrip_vision/sample_data`` in an installed wheel, else the source
    checkout's ``data/``."""
    packaged = resources.files("softgrip_vision") / "sample_data"
    if packaged.is_dir():
        return Path(str(packaged))
    return Path(__file__).resolve().parents[1] / "data"
