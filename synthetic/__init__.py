"""Test support, not installed: synthetic RGB-D scenes (``render``, ``scenes``, ``shapes``) and an
independent elastic-rod closure model (``rod``) for the tests, the benchmarks and
``data/make_samples.py``.

It lives in the source tree beside ``tests/`` and ``benchmarks/``, outside the packages ``pip``
installs: a user's program imports ``softgrip_jax``, ``softgrip_vision``, ``softgrip_calib`` and ``softgrip_cli``,
never the instrument that checks them. Importable from the root of a checkout (pytest puts the
root on ``sys.path``; the benchmark scripts and ``data/make_samples.py`` do so themselves).
"""
