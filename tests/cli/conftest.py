"""Fixtures of the command-line tests."""

import signal

import pytest


@pytest.fixture
def sigint_delivered():
    """Children of this test receive SIGINT as Ctrl-C does, however the test run was started: a
    shell starts a background job (``make test &``) with SIGINT ignored, every child
    inherits that, and Python installs no KeyboardInterrupt handler where it finds it ignored."""
    before = signal.getsignal(signal.SIGINT)
    if before == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)
