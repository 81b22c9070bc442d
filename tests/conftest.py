import jax
import pytest
from hypothesis import settings

# Property tests compile JAX functions on first use; the first example can take seconds.
settings.register_profile("softgrip", deadline=None, max_examples=30, derandomize=True, database=None)
settings.load_profile("softgrip")


@pytest.fixture
def x64():
    """Run the test in float64 (finite-difference comparisons), restoring the default after."""
    with jax.enable_x64(True):
        yield
