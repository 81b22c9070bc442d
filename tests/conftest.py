import os

import jax
import pytest
from hypothesis import settings

# The commands turn JAX's persistent compilation cache on (softgrip_jax.enable_compilation_cache);
# the tests run commands in-process, which would turn it on for the rest of the worker and write
# every program the suite compiles into the user's cache folder. Off for the suite; the tests of
# the cache itself turn it on for a temporary folder.
os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")

# Property tests compile JAX functions on first use; the first example can take seconds.
settings.register_profile("softgrip", deadline=None, max_examples=30, derandomize=True, database=None)
settings.load_profile("softgrip")


@pytest.fixture
def x64():
    """Run the test in float64 (finite-difference comparisons), restoring the default after."""
    with jax.enable_x64(True):
        yield
