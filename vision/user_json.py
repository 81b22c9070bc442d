"""Reading JSON written by people lives in :mod:`softgrip_base.user_json`; this import path keeps
working and names the same function."""

from softgrip_base.user_json import loads

__all__ = ["loads"]
