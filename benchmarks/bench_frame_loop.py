"""A planner's per-frame loop on the sample frame, and object_scene over arm poses (issue 42).

Run from the repository root (the compilation cache off, one process, a few minutes: the scoring
program compiles once, tens of seconds):

    .venv/bin/python benchmarks/bench_frame_loop.py
    .venv/bin/python benchmarks/bench_frame_loop.py --repeats 20 --poses 500

Rows:

* ``loop``: ``load_frame`` of ``data/circle_open``, ``frame_scene`` on it, ``Scene.score`` of 500
  poses near the scene's pose (uniform +-5 mm, +-0.1 rad; the default estimator): the median of each
  step over ``--repeats`` warm iterations (after one that compiles), and the loop's rate.
* ``score_frames``: the same loop through :func:`softgrip_vision.stream.score_frames`, which scores a
  frame on a worker thread while the next is loaded and measured: its rate (median of 3 runs of
  ``--repeats`` frames) and a frame's latency (from its load to its result).
* ``object_scene``: 10 arm poses of ``object_scene`` on a rendered 30 mm disc without the gripper in
  view (x and y tens of mm apart, the depth 116-124 mm), each followed by ``Scene.score`` of the same
  500 poses around its pose: the object grid's shapes, the programs the scoring entry point compiled
  after the first pose (``_score_one_device``'s cache; every XLA compilation as well, from
  ``jax_log_compiles``), and the median time of ``object_scene`` itself.

Prints Markdown rows, headed by the tree's commit and the machine.
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")

import jax  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout (and its synthetic renderer)
sys.path.insert(1, str(Path(__file__).resolve().parent))
from _machine import CompileCounter, describe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def near(pose: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.asarray(pose) + rng.uniform([-5.0, -5.0, -0.1], [5.0, 5.0, 0.1], (count, 3))


def loop_rows(repeats: int, count: int) -> None:
    from softgrip_calib.profile import load_profile
    from softgrip_vision.frames import load_frame
    from softgrip_vision.scene import frame_scene

    folder, profile = ROOT / "data" / "circle_open", load_profile(ROOT / "data" / "sample_profile.json")
    poses = near(frame_scene(folder, profile).pose, count)
    times: dict[str, list[float]] = {"load": [], "frame_scene": [], "score": [], "loop": []}
    for k in range(repeats + 1):
        t0 = time.perf_counter()
        frame = load_frame(folder)
        t1 = time.perf_counter()
        scene = frame_scene(frame, profile)
        t2 = time.perf_counter()
        scene.score(poses)  # numpy out: blocks until done
        t3 = time.perf_counter()
        if k == 0:
            print(f"| first iteration (compiles the scoring program) | {t3 - t0:.1f} s | |")
            continue
        for name, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
            times[name].append(dt)
    ms = {name: 1e3 * float(np.median(v)) for name, v in times.items()}
    print(f"| load_frame, circle_open | {ms['load']:.1f} ms | median of {repeats} |")
    print(f"| frame_scene, circle_open (a loaded Frame) | {ms['frame_scene']:.1f} ms | median of {repeats} |")
    print(f"| Scene.score, {count} poses, default estimator | {ms['score']:.1f} ms | median of {repeats} |")
    print(f"| loop: load -> frame_scene -> score {count} | {1e3 / ms['loop']:.2f} Hz ({ms['loop']:.0f} ms) | "
          f"score is {ms['score'] / ms['loop']:.0%} of it |")


def stream_rows(repeats: int, count: int) -> None:
    """The same loop through ``score_frames``: the next frame's load and ``frame_scene`` overlap the
    previous frame's score (a worker thread)."""
    from softgrip_calib.profile import load_profile
    from softgrip_vision.frames import load_frame
    from softgrip_vision.scene import frame_scene
    from softgrip_vision.stream import score_frames

    folder, profile = ROOT / "data" / "circle_open", load_profile(ROOT / "data" / "sample_profile.json")
    poses = near(frame_scene(folder, profile).pose, count)
    rates, latencies = [], []
    for _ in range(3):
        started: list[float] = []

        def frames():
            for _ in range(repeats):
                started.append(time.perf_counter())
                yield load_frame(folder)

        t0 = time.perf_counter()
        for k, _ in enumerate(score_frames(frames(), profile, poses)):
            latencies.append(time.perf_counter() - started[k])
        rates.append(repeats / (time.perf_counter() - t0))
    print(f"| score_frames: the same loop, the next frame measured while the last is scored | "
          f"{float(np.median(rates)):.2f} Hz | median of 3 runs of {repeats} frames; a frame's result "
          f"{1e3 * float(np.median(latencies)):.0f} ms after its load began (median) |")


def object_scene_rows(count: int) -> None:
    from softgrip_calib.profile import load_profile
    from softgrip_jax._score import _score_one_device
    from softgrip_vision.object_scene import object_scene
    from synthetic.render import Scene, d405_intrinsics, render

    a = np.linspace(0.0, 2.0 * np.pi, 128, endpoint=False)
    disc = np.stack([15.0 * np.cos(a), 5.0 + 15.0 * np.sin(a)], axis=-1)  # mm, in a plane 120 mm deep
    frame = render(Scene([], object_polygon=disc), d405_intrinsics())
    profile = load_profile(ROOT / "data" / "sample_profile.json")
    rng = np.random.default_rng(1)
    counter = CompileCounter()
    logging.getLogger("jax").addHandler(counter)
    shapes, times, programs, compiles = set(), [], 0, 0
    with jax.log_compiles(True):
        for k in range(10):
            t = np.eye(4)
            t[:3, 3] = [rng.uniform(-30.0, 30.0), -40.0 + rng.uniform(-30.0, 30.0), 120.0 + rng.uniform(-4.0, 4.0)]
            start = time.perf_counter()
            scene = object_scene(frame, profile, t, warn=lambda _: None)
            times.append(time.perf_counter() - start)
            shapes.add(tuple(scene.sdf.values.shape))
            if k == 0:
                scene.score(near(scene.pose, count))
                programs, compiles = _score_one_device._jitted._cache_size(), counter.count
            else:
                scene.score(near(scene.pose, count, seed=k))
    logging.getLogger("jax").removeHandler(counter)
    programs = _score_one_device._jitted._cache_size() - programs
    print(f"| object_scene, 10 arm poses: grid shapes | {sorted(shapes)} | |")
    print(f"| object_scene, 10 arm poses: scoring programs compiled after the first | {programs} | "
          f"every XLA compilation after the first pose: {counter.count - compiles} |")
    print(f"| object_scene, one arm pose | {1e3 * float(np.median(times[1:])):.0f} ms | median of 9 (the first: "
          f"{1e3 * times[0]:.0f} ms) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=10, help="warm loop iterations (default 10)")
    parser.add_argument("--poses", type=int, default=500, help="poses scored per frame (default 500)")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip() or "unknown"
    print(f"bench_frame_loop at {commit}; {describe()}")
    print()
    print("| what | figure | note |")
    print("|---|---|---|")
    loop_rows(args.repeats, args.poses)
    stream_rows(args.repeats, args.poses)
    object_scene_rows(args.poses)


if __name__ == "__main__":
    main()
