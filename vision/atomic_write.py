"""The output policy lives in :mod:`softgrip_base.atomic_write` (it is not vision: every command
writes through it); this import path keeps working and names the same objects."""

from softgrip_base.atomic_write import (FRAME_FILES, OutputRefusedError, atomic_open, check_output, frame_inputs,
                                        write_atomic)

__all__ = ["FRAME_FILES", "OutputRefusedError", "atomic_open", "check_output", "frame_inputs", "write_atomic"]
