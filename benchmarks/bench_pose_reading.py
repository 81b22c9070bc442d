"""How long reading pose files and frames takes through the input guard (softgrip_base.input_guard).

    python benchmarks/bench_pose_reading.py [--rows 1000000] [--repeat 3]

Times ``softgrip_cli.cmd_score.read_poses`` on a file of ROWS poses as plain CSV, CSV saved by a
spreadsheet (byte-order mark, ';' separators, CRLF) and JSON, and ``softgrip_vision.frames.load_frame`` /
``softgrip_calib.profile.load_profile`` on the sample data; best of REPEAT runs, seconds. Run it with
``PYTHONPATH`` pointing at another checkout to compare (a format that checkout refuses is shown as
"refused").
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def best_of(repeat: int, fn) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    from softgrip_calib.profile import load_profile
    from softgrip_cli.cmd_score import read_poses
    from softgrip_jax import SoftgripError
    from softgrip_vision.frames import load_frame

    sys.path.insert(0, str(ROOT))
    from benchmarks._machine import describe

    rng = np.random.default_rng(0)
    poses = np.round(rng.uniform([-20, -60, -0.3], [20, -30, 0.3], (args.rows, 3)), 3)
    rows = [f"{x:g},{y:g},{a:g}" for x, y, a in poses]
    files = {
        "plain.csv": ("x_mm,y_mm,angle_rad\n" + "\n".join(rows) + "\n").encode(),
        "excel.csv": ("\ufeffx_mm;y_mm;angle_rad\r\n" + "\r\n".join(r.replace(",", ";") for r in rows)
                      + "\r\n").encode("utf-8"),
        "poses.json": ("[" + ",\n".join(f"[{r}]" for r in rows) + "]").encode(),
    }
    print(describe())
    print(f"read_poses, {args.rows} poses, best of {args.repeat} (s):")
    with tempfile.TemporaryDirectory() as folder:
        for name, data in files.items():
            path = Path(folder) / name
            path.write_bytes(data)
            try:
                read = read_poses(str(path))
                assert np.allclose(read, poses), name
                seconds = f"{best_of(args.repeat, lambda: read_poses(str(path))):.2f}"
            except SoftgripError as err:
                seconds = f"refused ({str(err)[:60]}...)"
            print(f"  {name:<11} {len(data) / 2**20:6.1f} MiB  {seconds}")
    frame, profile = ROOT / "data" / "circle_open", ROOT / "data" / "sample_profile.json"
    load_frame(frame)
    load_profile(profile)
    print(f"load_frame(data/circle_open): {best_of(10, lambda: load_frame(frame)) * 1e3:.1f} ms, "
          f"load_profile(data/sample_profile.json): {best_of(10, lambda: load_profile(profile)) * 1e3:.1f} ms "
          f"(best of 10)")


if __name__ == "__main__":
    main()
