"""One line describing the machine and software a benchmark ran on, and the benchmarks' shared timer."""

import logging
import os
import platform
import time


def describe() -> str:
    import jax

    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.machine()}, "
            f"Python {platform.python_version()}, jax {jax.__version__} on {jax.default_backend()}")


def best_of(fn, k=3, warm=False):
    """The shortest of ``k`` timed calls of ``fn`` (s), each waited for (``jax.block_until_ready``);
    ``warm``: one untimed call first (its compilation)."""
    import jax

    if warm:
        jax.block_until_ready(fn())
    times = []
    for _ in range(k):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return min(times)


class CompileCounter(logging.Handler):
    """Counts the programs JAX compiles while installed (``jax_log_compiles`` messages)."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def emit(self, record):
        if record.getMessage().startswith("Finished XLA compilation"):
            self.count += 1
