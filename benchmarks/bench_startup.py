"""Start-up time of a new process: the README's planner example, ``refine``, and ``softgrip demo``.

Each case runs in a fresh Python process (nothing compiled in memory), first with an empty
compilation cache folder, then again with the folder that run filled (warm). Times are wall-clock
seconds of the whole process, imports included, from bytecode-compiled modules as an install
leaves them (``make setup`` writes the installed packages' bytecode; the measured tree's own
packages are compiled first).

    python benchmarks/bench_startup.py               # all cases
    python benchmarks/bench_startup.py planner refine
    python benchmarks/bench_startup.py --json
    python benchmarks/bench_startup.py planner --root /tmp/old-checkout   # another source tree's figures
    python benchmarks/bench_startup.py planner --log-compiles             # and where the cold time goes

Cases:
* ``planner``: the README's "A planner" example (score 605 poses geometrically, refine the best);
* ``refine``: ``refine`` alone, one pose, default (mechanics) estimate, as a library user calls it
  (``EQX_ON_ERROR=nan`` set as ``softgrip_jax.enable_compilation_cache`` advises) and once without it;
* ``demo``: ``softgrip demo --json`` through the command line, output to a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PLANNER = """
import softgrip_jax
softgrip_jax.enable_compilation_cache()
import jax.numpy as jnp
from softgrip_jax import CASE_NAMES, FingerModel, Geometric, Gripper, PolygonSDF, refine, score

finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)  # mm, rad
gripper = Gripper(left=finger, right=finger, base_separation=56.0)  # mm
obj = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)  # a 30 mm disc
x, y, angle = jnp.meshgrid(jnp.linspace(-10.0, 10.0, 11), jnp.linspace(-10.0, 10.0, 11),
                           jnp.linspace(-0.2, 0.2, 5), indexing="ij")
poses = jnp.stack([x.ravel(), y.ravel(), angle.ravel()], axis=-1)  # (605, 3)
result = score(gripper, obj, poses, estimator=Geometric())
best = int(jnp.argmax(result.score))
refined = refine(gripper, obj, poses[best], estimator=Geometric())
f = refined.score.grasp.left
print(CASE_NAMES[int(f.case)], [round(float(v), 1) for v in f.joints[-1]])
"""

REFINE = """
import softgrip_jax
softgrip_jax.enable_compilation_cache()
import jax.numpy as jnp
from softgrip_jax import FingerModel, Gripper, PolygonSDF, refine

finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=20)
gripper = Gripper(left=finger, right=finger, base_separation=56.0)
obj = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=128)
refined = refine(gripper, obj, jnp.array([1.0, 0.0, 0.0]))  # the mechanics estimate (default)
print(int(refined.status), [round(float(v), 2) for v in refined.pose])
"""


def _run(argv: list[str], env: dict[str, str], cwd: Path) -> tuple[float, str]:
    t0 = time.perf_counter()
    out = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=1800)
    elapsed = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"{argv} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return elapsed, out.stdout.strip()[-200:]


def _cold_then_warm(argv: list[str], extra_env: dict[str, str], cwd: Path) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="softgrip-cache-") as cache:
        env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache, **extra_env}
        env.pop("SOFTGRIP_JAX_CACHE", None)
        cold, _ = _run(argv, env, cwd)
        entries = len(list(Path(cache).iterdir()))
        warm, tail = _run(argv, env, cwd)
    return {"empty_cache_s": round(cold, 1), "warm_cache_s": round(warm, 1), "cache_entries": entries,
            "output_tail": tail}


def _compile_log(argv: list[str], extra_env: dict[str, str], cwd: Path) -> list[str]:
    """One more empty-cache run with ``JAX_LOG_COMPILES=1`` (apart from the timed ones, which log
    nothing): JAX's "Finished <tracing, lowering or XLA compilation of a program> in <s> sec" lines
    of 0.1 s or more, in order, as "<seconds> s <what>"."""
    with tempfile.TemporaryDirectory(prefix="softgrip-cache-") as cache:
        env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache, "JAX_LOG_COMPILES": "1", **extra_env}
        env.pop("SOFTGRIP_JAX_CACHE", None)
        out = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=1800, check=True)
    found = re.findall(r"Finished (.+?) in ([0-9.]+) sec", out.stderr)
    return [f"{float(seconds):.2f} s {what}" for what, seconds in found if float(seconds) >= 0.1]


def _byte_compile(root: Path) -> None:
    """Bytecode for the measured tree's own packages, as an install writes it (``make setup`` does
    so for the installed ones): no run then compiles them from source, also where
    PYTHONDONTWRITEBYTECODE is set, and two trees are compared on the same footing."""
    packages = [str(init.parent) for init in sorted(root.glob("*/__init__.py"))
                if init.parent.name not in ("tests", "benchmarks")]
    subprocess.run([sys.executable, "-m", "compileall", "-q", *packages], check=True, capture_output=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("cases", nargs="*", default=["planner", "refine", "demo"])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--log-compiles", action="store_true",
                        help="planner: also list what an empty-cache run traces, lowers and compiles, and for how long")
    parser.add_argument("--root", type=Path, default=ROOT,
                        help="the source tree to run (default: this one), e.g. a `git worktree` of an older commit")
    args = parser.parse_args()
    from benchmarks._machine import describe

    python = sys.executable
    root = args.root.resolve()
    pythonpath = {"PYTHONPATH": str(root)}
    results: dict[str, object] = {"machine": describe(), "root": str(root)}
    _byte_compile(root)
    for case in args.cases:
        if case == "planner":
            results["planner"] = _cold_then_warm([python, "-c", PLANNER], pythonpath, root)
            if args.log_compiles:
                results["planner_compile_log"] = _compile_log([python, "-c", PLANNER], pythonpath, root)
        elif case == "refine":
            results["refine_mechanics_eqx_nan"] = _cold_then_warm([python, "-c", REFINE],
                                                                 {**pythonpath, "EQX_ON_ERROR": "nan"}, root)
            results["refine_mechanics_eqx_raise"] = _cold_then_warm([python, "-c", REFINE],
                                                                  {**pythonpath, "EQX_ON_ERROR": "raise"}, root)
        elif case == "demo":
            with tempfile.TemporaryDirectory(prefix="softgrip-demo-") as out:
                argv = [python, "-m", "softgrip_cli", "demo", "--json", "--out", str(Path(out) / "demo")]
                cold_warm = {}
                with tempfile.TemporaryDirectory(prefix="softgrip-cache-") as cache:
                    env = {**os.environ, **pythonpath, "JAX_COMPILATION_CACHE_DIR": cache}
                    env.pop("SOFTGRIP_JAX_CACHE", None)
                    cold_warm["empty_cache_s"] = round(_run(argv, env, root)[0], 1)
                    cold_warm["cache_entries"] = len(list(Path(cache).iterdir()))
                    argv[-1] = str(Path(out) / "demo2")
                    cold_warm["warm_cache_s"] = round(_run(argv, env, root)[0], 1)
                results["demo"] = cold_warm
        else:
            parser.error(f"unknown case {case!r}")
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        for key, value in results.items():
            print(f"{key}: {value}")


if __name__ == "__main__":
    main()
