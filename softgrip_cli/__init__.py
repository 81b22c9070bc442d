"""The ``softgrip`` command line: the composition root wiring ``softgrip_jax``, ``softgrip_vision`` and ``softgrip_calib``.

It lives outside the three packages so that the core never imports the vision or calibration
packages. Each command is a module with an ``add_parser(subparsers)`` function.
"""

from softgrip_cli._main import main

__all__ = ["main"]
