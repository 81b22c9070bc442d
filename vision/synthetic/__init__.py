"""Deprecated: the synthetic renderer and rod moved to the test-support package ``synthetic`` at the
root of the source tree (not installed). From a checkout, ``vision.synthetic.render``, ``.rod``,
``.scenes`` and ``.shapes`` still name those modules, with a ``DeprecationWarning``; import
``synthetic.render`` etc. instead."""

import importlib
import sys
import warnings

warnings.warn("vision.synthetic is deprecated: import the test-support package `synthetic` (render, rod, "
              "scenes, shapes) from the root of a source checkout", DeprecationWarning, stacklevel=2)
try:
    for _name in ("render", "rod", "scenes", "shapes"):
        globals()[_name] = sys.modules[f"{__name__}.{_name}"] = importlib.import_module(f"synthetic.{_name}")
except ModuleNotFoundError as err:  # an installed copy: the test support is in the source tree only
    raise ModuleNotFoundError("vision.synthetic moved to the test-support package `synthetic` of the "
                              "softgrip-jax source tree (not installed): run from a checkout") from err
