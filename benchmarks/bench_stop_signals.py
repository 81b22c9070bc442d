"""What a stopped or starved `softgrip` leaves behind: the issue-32 reproducers of signals and of a
standard output that fails, run against a source tree (this one, or another checkout for the
figures before a change).

    python benchmarks/bench_stop_signals.py [--root PATH] [--grid SPEC]

For SIGTERM and SIGHUP: `softgrip score data/circle_open -o out.json --top 0 --grid SPEC`, the
signal sent the moment the hidden temporary file appears (the document is being written); reports
the exit status, the line on stderr, the files left in the output folder and the time from the
signal to the exit. Then `score ... --json` with stdout on /dev/full and with stdout closed, and
`softgrip --version > /dev/full`: the exit status and whether stderr holds a traceback.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def run_signal(root: Path, name: str, grid: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(root), "SOFTGRIP_JAX_CACHE": "0"}
    with tempfile.TemporaryDirectory() as folder:
        process = subprocess.Popen([sys.executable, "-m", "softgrip_cli", "score", str(root / "data" / "circle_open"),
                                    "--profile", str(root / "data" / "sample_profile.json"), "--method", "geometric",
                                    f"--grid={grid}", "--top", "0", "-o", os.path.join(folder, "out.json")],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=root)
        sent = None
        while process.poll() is None:
            if sent is None and any(n.endswith(".tmp") for n in os.listdir(folder)):
                process.send_signal(getattr(signal, name))
                sent = time.monotonic()
            time.sleep(0.005)
        _, err = process.communicate()
        left = {n: os.path.getsize(os.path.join(folder, n)) for n in os.listdir(folder)}
    lines = err.decode(errors="replace").strip().splitlines()
    return {"signal": name, "sent": sent is not None, "exit": process.returncode,
            "stderr_last": lines[-1] if lines else "", "traceback": "Traceback" in err.decode(errors="replace"),
            "left": left, "exit_after_s": round(time.monotonic() - sent, 2) if sent else None}


def run_stdout(root: Path, case: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(root), "SOFTGRIP_JAX_CACHE": "0"}
    argv = [sys.executable, "-m", "softgrip_cli"]
    argv += (["--version"] if case == "version-full" else
             ["score", str(root / "data" / "circle_open"), "--profile", str(root / "data" / "sample_profile.json"),
              "--method", "geometric", "--grid=-5:5:3,-60:-40:3,0:0:1", "--json"])
    with open("/dev/full", "wb") as full:
        kwargs = {"stdout": full} if case.endswith("full") else {"stdout": subprocess.DEVNULL,
                                                                   "preexec_fn": lambda: os.close(1)}
        run = subprocess.run(argv, stderr=subprocess.PIPE, env=env, cwd=root, **kwargs)
    text = run.stderr.decode(errors="replace")
    lines = [line for line in text.splitlines() if line.strip()]
    return {"case": case, "exit": run.returncode, "traceback": "Traceback" in text,
            "stderr_last": lines[-1][:160] if lines else ""}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=HERE, help="the source tree to run (default: this one)")
    parser.add_argument("--grid", default="-10:10:20,-60:-30:20,-0.1:0.1:10", help="score's --grid")
    args = parser.parse_args()
    for name in ("SIGTERM", "SIGHUP"):
        print(run_signal(args.root.resolve(), name, args.grid), flush=True)
    for case in ("score-json-full", "score-json-closed", "version-full"):
        print(run_stdout(args.root.resolve(), case), flush=True)


if __name__ == "__main__":
    main()
