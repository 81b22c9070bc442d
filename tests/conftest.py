import gc
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


#: Memory maps of this process above which the compiled programs are dropped after a test file.
MAX_MAPS_KEPT = 30_000


def _memory_maps() -> int | None:
    """How many memory maps this process holds (Linux), or None where ``/proc`` does not say."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return None


@pytest.fixture(autouse=True, scope="module")
def release_compiled_programs():
    """Drop JAX's compiled programs after a test file once the process holds many memory maps.

    XLA:CPU maps memory for every compiled program: about 740 maps for a small ``estimate_batch``
    program, as ``/proc/self/maps`` counts them. A pytest worker that keeps the whole suite's
    programs reaches Linux's limit of memory maps per process (``vm.max_map_count``, 65,530 by
    default); XLA then fails to map memory and crashes inside a compile (a segfault or an abort).
    Below :data:`MAX_MAPS_KEPT` the programs stay, shared by the files a worker runs next."""
    yield
    maps = _memory_maps()
    if maps is not None and maps > MAX_MAPS_KEPT:
        jax.clear_caches()
        gc.collect()


@pytest.fixture
def x64():
    """Run the test in float64 (finite-difference comparisons), restoring the default after."""
    with jax.enable_x64(True):
        yield
