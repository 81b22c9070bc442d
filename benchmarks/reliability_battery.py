"""A battery of bad inputs against the `softgrip` command (issue 21): each kind is run in this
process through `softgrip_cli.main`, and classified as

* clean: a one-line error (exit 2, no traceback) or the documented outcome, and nothing lost;
* traceback: any other exception, or exit 1;
* data lost: an input, or a file the run must not replace, changed or turned into another kind.

Run: python benchmarks/reliability_battery.py [--json]   (from the repository root; needs no camera)
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import stat
import struct
import sys
import tempfile
import traceback
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT / "data"
PROFILE = str(DATA / "sample_profile.json")


def run(argv):
    from softgrip_cli import main

    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    except SystemExit as exc:
        code = exc.code
    except BaseException:  # noqa: BLE001 - a traceback is what the battery counts
        return 1, out.getvalue(), err.getvalue() + traceback.format_exc()
    return code, out.getvalue(), err.getvalue()


def fingerprint(path: Path):
    st = os.lstat(path) if os.path.lexists(path) else None
    if st is None:
        return None
    data = hashlib.sha1(path.read_bytes()).hexdigest() if stat.S_ISREG(st.st_mode) else None
    return stat.S_IFMT(st.st_mode), stat.S_IMODE(st.st_mode), data


def frame(tmp: Path, name="circle_open", **intrinsics) -> Path:
    folder = tmp / f"{name}_{len(list(tmp.iterdir()))}"
    shutil.copytree(DATA / name, folder)
    if intrinsics:
        data = json.loads((folder / "intrinsics.json").read_text())
        data.update(intrinsics)
        (folder / "intrinsics.json").write_text(json.dumps(data))
    return folder


def png_header(width, height) -> bytes:
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def kinds(tmp: Path):
    """(name, argv, files that must not change, expected exit code)."""
    out = []
    f = frame(tmp)
    out.append(("calibrate -o onto its open frame", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "-o",
                                                     str(f / "intrinsics.json")], [f / "intrinsics.json"], 2))
    out.append(("calibrate -o onto its open frame, --force", ["calibrate", str(DATA / "calib_closed"), "--open", str(f),
                                                              "-o", str(f / "depth.png"), "--force"], [f / "depth.png"], 2))
    out.append(("score --heatmap onto the frame's image", ["score", str(f), "--profile", PROFILE, "--heatmap",
                                                          str(f / "color.png")], [f / "color.png"], 2))
    out.append(("score -o onto the profile", ["score", str(f), "--profile", PROFILE, "-o", PROFILE], [Path(PROFILE)], 2))
    hard = tmp / "hard.png"
    os.link(f / "color.png", hard)
    out.append(("score --heatmap onto a hard link of the image", ["score", str(f), "--profile", PROFILE, "--heatmap",
                                                                 str(hard)], [f / "color.png"], 2))
    fifo = tmp / "fifo"
    os.mkfifo(fifo)
    out.append(("calibrate -o onto a FIFO", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "-o", str(fifo)],
                [fifo], 2))
    out.append(("calibrate -o onto /dev/full", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "-o",
                                                "/dev/full", "--force"], [Path("/dev/full")], 2))
    real, link = tmp / "real.json", tmp / "link.json"
    real.write_text("{}")
    link.symlink_to(real.name)
    out.append(("calibrate -o onto a symlink", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "-o",
                                                str(link)], [link, real], 2))
    out.append(("calibrate -o onto a folder", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "-o",
                                               str(tmp)], [], 2))
    for field, value in (("depth_scale", 1000), ("depth_scale", 1e-9), ("fx", 1e300), ("fx", 1e-300), ("fy", 1e4),
                         ("ppx", 1e9), ("ppy", -1e6)):
        g = frame(tmp, **{field: value})
        out.append((f"estimate with {field} = {value:g}", ["estimate", str(g), "--profile", PROFILE], frame_files(g), 2))
        out.append((f"calibrate with {field} = {value:g}", ["calibrate", str(DATA / "calib_closed"), "--open", str(g),
                                                           "-o", str(tmp / "x.json")], frame_files(g), 2))
    for w, h, what in ((60000, 60000, "a 60000x60000 header"), (20000, 20000, "a 20000x20000 header"),
                       (0, 480, "a zero width")):
        g = frame(tmp)
        (g / "color.png").write_bytes(png_header(w, h))
        out.append((f"estimate, color.png with {what}", ["estimate", str(g), "--profile", PROFILE], frame_files(g), 2))
    g = frame(tmp)
    (g / "depth.png").unlink()
    os.mkfifo(g / "depth.png")
    out.append(("estimate, depth.png is a FIFO", ["estimate", str(g), "--profile", PROFILE], [], 2))
    out.append(("calibrate --fit CLOSED OPEN (swapped)", ["calibrate", "--fit", str(DATA / "circle_closed"),
                                                         str(DATA / "circle_open"), "-o", str(tmp / "sw.json")], [], 2))
    out.append(("calibrate --n-links 10**6", ["calibrate", str(DATA / "calib_closed"), "--open", str(f), "--n-links",
                                              str(10**6), "-o", str(tmp / "n.json")], [], 2))
    bad = tmp / "bad.json"
    bad.write_text("[[1, 2, 3], [4, true, 6]]")
    out.append(("score --poses with a boolean", ["score", str(f), "--profile", PROFILE, "--poses", str(bad)], [bad], 2))
    huge = tmp / "huge.json"
    huge.write_text(json.dumps([[1e400 if i == 5 else 1.0, 2.0, 0.0] for i in range(10)]).replace("Infinity", "1e400"))
    out.append(("score --poses with 1e400", ["score", str(f), "--profile", PROFILE, "--poses", str(huge)], [huge], 2))
    out.append(("capture --allow-partial with a camera", ["capture", "--out", str(tmp / "cap"), "--allow-partial"], [], 2))
    return out


def frame_files(folder: Path):
    return [folder / n for n in ("color.png", "depth.png", "intrinsics.json")]


def main() -> int:
    os.environ.setdefault("SOFTGRIP_JAX_CACHE", "0")
    results = []
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        for name, argv, keep, expected in kinds(tmp):
            before = [fingerprint(p) for p in keep]
            code, _, err = run(argv)
            lost = [str(p) for p, b in zip(keep, before) if fingerprint(p) != b]
            outcome = ("data lost" if lost else "traceback" if code == 1 or "Traceback" in err
                       else "clean" if code == expected and len(err.strip().splitlines()) >= 1 else f"exit {code}")
            results.append({"kind": name, "outcome": outcome, "exit": code, "lost": lost,
                            "message": err.strip().splitlines()[-1][:200] if err.strip() else ""})
    counts = {k: sum(r["outcome"] == k for r in results) for k in ("clean", "traceback", "data lost")}
    counts["other"] = len(results) - sum(counts.values())
    if "--json" in sys.argv:
        print(json.dumps({"kinds": len(results), **counts, "results": results}, indent=1))
    else:
        for r in results:
            print(f"{r['outcome']:<9} {r['kind']}: {r['message']}")
        print(f"{len(results)} kinds: {counts['clean']} clean, {counts['traceback']} traceback, "
              f"{counts['data lost']} data lost, {counts['other']} other")
    return 0 if counts["clean"] == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
