"""The bottom layer, below the JAX core: the error every user-caused failure derives from, and the
file helpers every command shares (atomic output, the input guard every file a person names is
read through, reading JSON written by people, messages safe to print).

It imports the standard library only (neither JAX, nor NumPy, nor OpenCV), so that any part of the
project can raise, catch and report a :class:`SoftgripError` without importing JAX; ``softgrip
capture`` reports a camera error this way.
"""

from softgrip_base.atomic_write import OutputRefusedError
from softgrip_base.errors import SoftgripError
from softgrip_base.input_guard import one_line, read_user_file

__all__ = ["OutputRefusedError", "SoftgripError", "one_line", "read_user_file"]
