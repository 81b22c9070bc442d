"""``SoftgripError`` lives in :mod:`softgrip_base.errors`, below the JAX core; this import path
keeps working and names the same class."""

from softgrip_base.errors import SoftgripError

__all__ = ["SoftgripError"]
