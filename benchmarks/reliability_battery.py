"""A battery of bad inputs, hostile files and hostile environments against the `softgrip` command
and its library (issues 21 and 32). Each kind declares its expected outcome; the run is classified by
:func:`classify` as the first of these that applies:

* code executed: a planted payload (a pickle that creates a marker file) ran: the marker exists;
* secret printed: a planted secret (a file standing for /etc/shadow) appears on stdout or stderr;
* crash: the process died by a signal (exit < 0, or >= 128 other than the expected 130 / 143 /
  141 / the signal the battery sent);
* traceback: exit 1, "Traceback" on stderr, or an exception escaping ``softgrip_cli.main``;
* hang: no exit within the kind's time limit (the process is killed);
* partial file: a new file in the output folder that is empty, a hidden ``.*.tmp``, or a JSON file
  that does not parse; or JSON on stdout that does not parse (truncated);
* data lost: an input, or a file the run must not replace, changed or turned into another kind;
* silent result: exit 0 with a result (``"valid": true`` in the JSON, or an output written) for a
  kind that must be refused or flagged ``valid: false``;
* unsanitised: escape bytes, or a line injected through a file name, reach the terminal;
* wrong outcome: another exit code than expected, a refusal whose message does not name the
  declared cause, or a refusal that comes only after the work;
* clean: none of the above.

Expectations: ``refuse`` (exit 2 with a one-line message), ``ok`` (exit 0; e.g. a CSV with a BOM
is read), ``either`` (exit 0 or 2), ``flag`` (exit 2, or exit 0 with no ``"valid": true``),
``signal`` (interrupted: 130 / 143 or death by the signal sent, or 0 if it finished first).

Most kinds run in this process through ``softgrip_cli.main`` (one JAX import, compiled programs
shared); those that can crash the process, read environment variables at import, need a closed or
full stdout, a signal, a resource limit or a blocking input run as ``python -m softgrip_cli`` in a
subprocess (with a 6 GB address-space limit and a time limit). Every run uses one compilation
cache folder of its own (warm after the first kinds). Inputs are built in a temporary folder;
nothing is written into the repository.

Run (from the repository root; needs no camera; about 30 minutes on a shared 2-core CPU, 3 with --in-process):

    python benchmarks/reliability_battery.py [--json] [--only SUBSTRING] [--list] [--seed N]

Exit 0 only when every kind is clean.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import io
import json
import os
import pickle
import random
import re
import resource
import shutil
import signal
import stat
import struct
import subprocess
import sys
import tempfile
import time
import traceback
import zlib
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT / "data"
PROFILE = str(DATA / "sample_profile.json")
#: Planted in files that stand for secrets (/etc/shadow): it must never be printed.
SECRET = "SECRET-battery-7f3a91c4"
SHADOW_TEXT = f"root:$6${SECRET}$Qx0:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n"
#: A small grid (9 poses; every batch up to 2048 poses shares one compiled program).
GRID = "--grid=-5:5:3,-60:-50:3,0:0:1"
GEOMETRIC = ("--method", "geometric")
#: The six counts issue 32 must bring to zero.
SIX = ("traceback", "crash", "silent result", "code executed", "secret printed", "partial file")
#: Every outcome, in the order the classifier tries them.
OUTCOMES = ("code executed", "secret printed", "crash", "traceback", "hang", "partial file", "data lost",
            "silent result", "unsanitised", "wrong outcome", "clean", "skipped")
EXPECTATIONS = ("refuse", "ok", "either", "flag", "signal")
#: Address-space limit of every subprocess (bytes): reading /dev/zero fails instead of eating the machine.
SUBPROCESS_MEMORY = 6 * 2**30


@dataclasses.dataclass
class Kind:
    """One fault kind: what to run, what must come of it, what to watch.

    ``argv``: the ``softgrip`` words (str or bytes), or None with ``call`` (a library call: it
    returns normally for exit 0; a ``SoftgripError`` is exit 2; anything else a traceback).
    ``message``: a regular expression (case-insensitive) the stderr must match when the command
    refuses (exit 2), or for ``ok`` kinds when it succeeds (a warning). ``keep``: files that must not
    change. ``watch``: output folders (new files there are results; checked for partial files).
    ``secret`` / ``marker``: the planted secret and payload marker file. ``subprocess``: run as
    ``python -m softgrip_cli``; then ``env`` (None unsets a variable), ``stdout`` (``pipe``,
    ``full`` = /dev/full, ``closed``, ``head`` = a pipe closed after 100 bytes), ``stdin`` (bytes),
    ``send`` (signal, delay s, or ``"tmp"``: as soon as a hidden ``.*.tmp`` appears in ``watch``), ``fsize`` (file-size limit, bytes: a full disk) and ``timeout`` (s).
    ``setup``: called just before the run (heavy inputs, planted cache files). ``check``: called
    with (observation, stdout of earlier kinds by name); returns (outcome, problem) or None.
    ``max_seconds``: a refusal after longer is a wrong outcome (it must come before the work).
    ``skip``: a reason not to run here. ``source``: ``21``, ``32`` (the issue's list) or ``new``.
    ``program``: the command a subprocess kind runs instead of ``python -m softgrip_cli`` (``argv``
    is appended; the tests feed the classifier broken commands this way).
    """

    name: str
    argv: list | None = None
    expect: str = "refuse"
    message: str = ""
    keep: list = dataclasses.field(default_factory=list)
    watch: list = dataclasses.field(default_factory=list)
    secret: str | None = None
    marker: Path | None = None
    subprocess: bool = False
    env: dict = dataclasses.field(default_factory=dict)
    stdout: str = "pipe"
    stdin: bytes | None = None
    send: tuple | None = None
    fsize: int | None = None
    timeout: float = 240.0
    call: Callable | None = None
    setup: Callable | None = None
    check: Callable | None = None
    max_seconds: float | None = None
    cwd: Path | None = None
    skip: str = ""
    source: str = "new"
    program: list | None = None


@dataclasses.dataclass
class Observation:
    """What a run did. ``code``: exit code (negative: killed by that signal; None: timed out)."""

    code: int | None
    stdout: str = ""
    stderr: str = ""
    escaped: bool = False
    seconds: float = 0.0
    new_files: list = dataclasses.field(default_factory=list)  # [(relative name, size)]
    bad_json: list = dataclasses.field(default_factory=list)  # new .json files that do not parse
    valid_in_files: bool = False  # a new JSON file says "valid": true
    lost: list = dataclasses.field(default_factory=list)
    marker: bool = False


VALID_TRUE = re.compile(r'"valid"\s*:\s*true')
INJECTED = re.compile(r"^(warning: )?INJECTED", re.MULTILINE)


def allowed_exits(kind: Kind) -> set:
    codes = {"refuse": {2}, "ok": {0}, "either": {0, 2}, "flag": {0, 2}, "signal": {0, 130, 143}}[kind.expect]
    if kind.send is not None:
        codes |= {128 + kind.send[0], -kind.send[0]}
    if kind.stdout in ("closed", "head", "full"):
        codes |= {141}  # the command's exit for an output pipe closed early
    return codes


def stdout_json_problem(kind: Kind, stdout: str) -> str | None:
    """Why the JSON on stdout does not parse (None when it does, or is not JSON output)."""
    words = [w for w in (kind.argv or []) if isinstance(w, str)]
    to_stdout = "-o" in words and words[words.index("-o") + 1:][:1] == ["-"]
    if not stdout.strip() or kind.stdout == "head" or not ({"--json", "--jsonl"} & set(words) or to_stdout):
        return None
    try:
        if "--jsonl" in words:
            for line in stdout.splitlines():
                if line.strip():
                    json.loads(line)
        else:
            json.loads(stdout)
    except ValueError as err:
        return f"stdout JSON does not parse ({err.__class__.__name__} at {len(stdout)} chars: truncated?)"
    return None


def classify(kind: Kind, obs: Observation, outputs: dict | None = None) -> tuple[str, list]:
    """(outcome, problems): the first outcome of :data:`OUTCOMES` that applies, and every problem
    found (each ``"<outcome>: <detail>"``)."""
    problems: list[tuple[str, str]] = []
    text = obs.stdout + obs.stderr
    allowed = allowed_exits(kind)
    if obs.marker:
        problems.append(("code executed", f"the payload's marker {kind.marker} exists"))
    if kind.secret and kind.secret in text:
        problems.append(("secret printed", "the planted secret is on " + ("stdout" if kind.secret in obs.stdout
                                                                           else "stderr")))
    if obs.code is not None and (obs.code < 0 or obs.code >= 128) and obs.code not in allowed:
        what = f"killed by signal {-obs.code}" if obs.code < 0 else f"exit {obs.code}"
        problems.append(("crash", what))
    if obs.code == 1 or "Traceback (most recent call last)" in obs.stderr or obs.escaped:
        errors = re.findall(r"^[\w.]+(?:Error|Exception|Interrupt|Exit)\b.*$", obs.stderr, re.MULTILINE)
        last = errors or [line for line in obs.stderr.strip().splitlines() if line.strip()]
        problems.append(("traceback", last[-1][:160] if last else f"exit {obs.code}"))
    if obs.code is None:
        problems.append(("hang", f"no exit within {kind.timeout:g} s (killed)"))
    partial = [f"{name} ({size} bytes)" for name, size in obs.new_files
               if size == 0 or (Path(name).name.startswith(".") and ".tmp" in Path(name).name)]
    partial += [f"{name} does not parse" for name in obs.bad_json]
    json_problem = stdout_json_problem(kind, obs.stdout)
    if json_problem:
        partial.append(json_problem)
    if partial:
        problems.append(("partial file", "; ".join(partial)))
    if obs.lost:
        problems.append(("data lost", ", ".join(obs.lost)))
    if kind.expect in ("refuse", "flag") and obs.code == 0:
        valid = VALID_TRUE.search(obs.stdout) or obs.valid_in_files
        produced = obs.new_files or obs.stdout.strip()
        if valid or (kind.expect == "refuse" and produced):
            problems.append(("silent result", "exit 0 with " + ('"valid": true' if valid else "a result")))
    if "\x1b" in text or INJECTED.search(text):
        problems.append(("unsanitised", "escape bytes or an injected line printed raw"))
    if kind.check is not None and obs.code == 0:
        found = kind.check(obs, outputs or {})
        if found:
            problems.append(found)
    if obs.code is not None and obs.code not in allowed and not any(p[0] in ("crash", "traceback")
                                                                     for p in problems):
        problems.append(("wrong outcome", f"exit {obs.code}, expected {kind.expect} ({'/'.join(map(str, sorted(allowed)))})"))
    elif kind.message and (obs.code == 2 or (kind.expect == "ok" and obs.code == 0)) \
            and not re.search(kind.message, obs.stderr, re.IGNORECASE):
        problems.append(("wrong outcome", f"the message does not match /{kind.message}/"))
    if kind.max_seconds is not None and obs.code == 2 and obs.seconds > kind.max_seconds:
        problems.append(("wrong outcome", f"refused only after {obs.seconds:.0f} s (must be checked before the work, "
                                          f"< {kind.max_seconds:g} s)"))
    if not problems:
        return "clean", []
    first = min(problems, key=lambda p: OUTCOMES.index(p[0]))[0]
    return first, [f"{o}: {d}" for o, d in problems]


# -- running ------------------------------------------------------------------------------------


def fingerprint(path: Path):
    st = os.lstat(path) if os.path.lexists(path) else None
    if st is None:
        return None
    data = hashlib.sha1(path.read_bytes()).hexdigest() if stat.S_ISREG(st.st_mode) else None
    return stat.S_IFMT(st.st_mode), stat.S_IMODE(st.st_mode), data


def snapshot(folders) -> dict:
    files = {}
    for folder in folders:
        for dirpath, _, names in os.walk(folder):
            for name in names:
                path = Path(dirpath) / name
                with contextlib.suppress(OSError):
                    files[path] = os.lstat(path).st_size
    return files


def run_in_process(kind: Kind) -> Observation:
    from softgrip_base import SoftgripError
    from softgrip_cli import main

    out, err = io.StringIO(), io.StringIO()
    escaped = False
    start = time.monotonic()
    previous = os.getcwd()
    try:
        if kind.cwd:
            os.chdir(kind.cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            if kind.argv is not None:
                code = main([os.fsdecode(w) for w in kind.argv])
            else:
                try:
                    kind.call()
                    code = 0
                except SoftgripError as error:
                    print(f"error: {error}", file=sys.stderr)
                    code = 2
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
    except BaseException:  # noqa: BLE001 - a traceback is what the battery counts
        code, escaped = 1, True
        err.write(traceback.format_exc())
    finally:
        os.chdir(previous)
    return Observation(code, out.getvalue(), err.getvalue(), escaped, time.monotonic() - start)


def run_subprocess(kind: Kind, env: dict, scratch: Path) -> Observation:
    env = dict(env)
    for key, value in kind.env.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value

    # Limits and a closed stdout set by the shell that then runs the command (no Python code runs
    # between fork and exec in this multithreaded process).
    shell = f"ulimit -v {SUBPROCESS_MEMORY // 1024}; "
    if kind.fsize is not None:
        shell += f"ulimit -f {max(1, kind.fsize // 512)}; "
    shell += 'exec "$@"' + (" 1>&-" if kind.stdout == "closed" else "")

    out_path, err_path = scratch / "stdout", scratch / "stderr"
    program = kind.program or [sys.executable, "-m", "softgrip_cli"]
    command = ["/bin/sh", "-c", shell, "sh", *program, *[os.fsencode(w) for w in kind.argv]]
    with open(err_path, "wb") as err_file, contextlib.ExitStack() as stack:
        if kind.stdout == "full":
            stdout = stack.enter_context(open("/dev/full", "wb"))
        elif kind.stdout == "head":
            stdout = subprocess.PIPE
        else:
            stdout = stack.enter_context(open(out_path, "wb"))
        start = time.monotonic()
        process = subprocess.Popen(command, stdin=subprocess.PIPE if kind.stdin is not None else subprocess.DEVNULL,
                                   stdout=stdout, stderr=err_file, env=env, cwd=kind.cwd or ROOT,
                                   start_new_session=True)
        head = b""
        if kind.stdin is not None:
            with contextlib.suppress(BrokenPipeError):
                process.stdin.write(kind.stdin)
            process.stdin.close()
        if kind.stdout == "head":
            head = process.stdout.read(100)
            process.stdout.close()
        code = None
        try:
            if kind.send is not None and kind.send[1] == "tmp":
                # The signal the moment a hidden temporary output appears (the write is under way).
                deadline = time.monotonic() + kind.timeout
                while code is None and time.monotonic() < deadline:
                    if any(Path(name).name.startswith(".") and ".tmp" in Path(name).name
                           for name in snapshot(kind.watch)):
                        process.send_signal(kind.send[0])
                        break
                    time.sleep(0.005)
                    code = process.poll()
            elif kind.send is not None:
                try:
                    code = process.wait(timeout=kind.send[1])
                except subprocess.TimeoutExpired:
                    process.send_signal(kind.send[0])
            if code is None:
                code = process.wait(timeout=kind.timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            code = None
        seconds = time.monotonic() - start
    stdout_text = head.decode("utf-8", "replace") if kind.stdout == "head" else (
        out_path.read_bytes().decode("utf-8", "replace") if out_path.exists() and kind.stdout == "pipe" else "")
    return Observation(code, stdout_text, err_path.read_bytes().decode("utf-8", "replace"), seconds=seconds)


def observe(kind: Kind, env: dict, scratch: Path, outputs: dict) -> tuple[str, list, Observation]:
    if kind.setup is not None:
        kind.setup()
    before = [fingerprint(p) for p in kind.keep]
    existing = snapshot(kind.watch)
    obs = run_subprocess(kind, env, scratch) if kind.subprocess else run_in_process(kind)
    obs.lost = [str(p) for p, b in zip(kind.keep, before) if fingerprint(p) != b]
    for path, size in snapshot(kind.watch).items():
        if path in existing:
            continue
        name = os.fsdecode(path)
        obs.new_files.append((name, size))
        if path.suffix == ".json" and size:
            try:
                text = path.read_text()
                json.loads(text)
                obs.valid_in_files |= bool(VALID_TRUE.search(text))
            except (OSError, ValueError):
                obs.bad_json.append(name)
    obs.marker = kind.marker is not None and kind.marker.exists()
    outputs[kind.name] = obs.stdout
    outcome, problems = classify(kind, obs, outputs)
    return outcome, problems, obs


# -- building the inputs ------------------------------------------------------------------------


class Builder:
    """Makes fault inputs in ``tmp`` (never in the repository)."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.count = 0
        self.shadow = tmp / "shadow"  # stands for /etc/shadow
        self.shadow.write_text(SHADOW_TEXT)

    def name(self, stem: str) -> Path:
        self.count += 1
        return self.tmp / f"{stem}_{self.count}"

    def outdir(self) -> Path:
        folder = self.name("out")
        folder.mkdir()
        return folder

    def frame(self, source="circle_open", name: str | bytes | None = None, **intrinsics) -> Path:
        if name is None:
            folder = self.name(source)
        else:  # a name of the user's (str, or bytes that need not be UTF-8)
            self.count += 1
            folder = Path(os.fsdecode(os.fsencode(self.tmp) + b"/n%d_" % self.count + os.fsencode(name)))
        shutil.copytree(DATA / source, folder)
        if intrinsics:
            data = json.loads((folder / "intrinsics.json").read_text())
            data.update(intrinsics)
            data = {k: v for k, v in data.items() if v is not None}
            (folder / "intrinsics.json").write_text(json.dumps(data))
        return folder

    def image_frame(self, change: Callable, which="color.png", **intrinsics) -> Path:
        import cv2

        folder = self.frame(**intrinsics)
        image = cv2.imread(str(folder / which), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(folder / which), change(image))
        return folder

    def profile(self, change: Callable) -> Path:
        data = json.loads(Path(PROFILE).read_text())
        change(data)
        path = self.name("profile").with_suffix(".json")
        path.write_text(json.dumps(data))
        return path

    def file(self, stem: str, content: str | bytes) -> Path:
        self.count += 1
        path = self.tmp / f"f{self.count}_{stem}"
        path.write_bytes(content.encode() if isinstance(content, str) else content)
        return path


def frame_files(folder: Path):
    return [folder / n for n in ("color.png", "depth.png", "intrinsics.json")]


def png_header(width, height) -> bytes:
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


class _Payload:
    """Unpickling it creates the marker file: code executed."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def plant(cache: Path, planted: Path, variant: str, marker: Path, decoy: Path) -> None:
    """A copy of the warm cache folder ``cache`` at ``planted`` whose exported programs are replaced
    by ``variant`` (see :func:`cache_kinds`)."""
    from softgrip_jax._export import EXPORT_SUBFOLDER, MAGIC

    shutil.rmtree(planted, ignore_errors=True)
    shutil.copytree(cache, planted, symlinks=True)
    payload = pickle.dumps(_Payload(marker))
    decoy.write_bytes(payload)
    folder = planted / EXPORT_SUBFOLDER
    files = sorted(folder.glob("*.export"))
    if not files:
        raise RuntimeError(f"no exported program in {folder} to replace (the baseline kind did not run)")
    for path in files:
        data = path.read_bytes()
        end = data.index(b"\n", len(MAGIC))
        header, body = json.loads(data[len(MAGIC):end]), data[end + 1:]

        def with_header(body_bytes, **fields):
            new = {**header, "size": len(body_bytes), "sha256": hashlib.sha256(body_bytes).hexdigest(), **fields}
            return MAGIC + json.dumps(new).encode() + b"\n" + body_bytes

        if variant == "pickle":
            path.write_bytes(payload)
        elif variant == "header claims a pickle":
            path.write_bytes(with_header(payload, format=1, serializer="pickle"))
        elif variant == "valid header, pickle body":
            path.write_bytes(with_header(payload))
        elif variant == "hash mismatch":
            path.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))
        elif variant == "header hash of a pickle":
            path.write_bytes(MAGIC + json.dumps(header).encode() + b"\n" + payload)
        elif variant == "symlink":
            path.unlink()
            path.symlink_to(decoy)
        elif variant == "foreign class in outputs":
            path.write_bytes(with_header(body, outputs={"module": "os:system", "fields": {}}))
        elif variant == "group-writable export folder":
            path.write_bytes(payload)
        elif variant == "world-writable cache folder":
            path.write_bytes(payload)
        else:
            raise ValueError(variant)
    if variant == "group-writable export folder":
        folder.chmod(0o770)
    if variant == "world-writable cache folder":
        planted.chmod(0o777)


def cache_kinds(b: Builder, cache: Path) -> list[Kind]:
    """The exported-program cache: each planted entry must be ignored (one warning), the command
    still succeeds, and the payload never runs."""
    out = []
    # Each costs a new trace of score (tens of seconds): the variants that differ in what they test.
    for variant in ("pickle", "header claims a pickle", "valid header, pickle body", "hash mismatch", "symlink",
                    "foreign class in outputs", "world-writable cache folder"):
        planted, marker, decoy = b.name("planted"), b.name("marker"), b.name("decoy")
        out.append(Kind(
            f"cache: exported program replaced ({variant})",
            ["score", str(DATA / "circle_open"), "--profile", PROFILE, GRID, *GEOMETRIC, "--json"],
            expect="ok", message=r"cach|export", marker=marker, subprocess=True,
            env={"JAX_COMPILATION_CACHE_DIR": str(planted)}, source="32",
            setup=lambda p=planted, v=variant, m=marker, d=decoy: plant(cache, p, v, m, d)))
    return out


def same_estimate(baseline: str) -> Callable:
    """A check: the estimate must differ from ``baseline``'s (the kind's input must change it)."""
    def check(obs: Observation, outputs: dict):
        try:
            mine = json.loads(obs.stdout)["frames"][0]["fingers"]
            theirs = json.loads(outputs[baseline])["frames"][0]["fingers"]
        except (KeyError, ValueError, IndexError, TypeError):
            return None
        if [f["joints_mm"] for f in mine] == [f["joints_mm"] for f in theirs]:
            return ("silent result", f"output identical to '{baseline}': the input was ignored")
        return None
    return check


def kinds(tmp: Path, cache: Path, rng: random.Random) -> list[Kind]:
    b = Builder(tmp)
    out: list[Kind] = []
    add = out.append
    P = PROFILE
    CIRCLE = str(DATA / "circle_open")

    # -- baselines: what the command does with good input (and the programs later kinds reuse) --
    add(Kind("baseline: score, a small grid", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "--json"],
             expect="ok", source="baseline"))
    add(Kind("baseline: estimate", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"], expect="ok",
             source="baseline"))

    # -- issue 21's kinds -------------------------------------------------------------------------
    f = b.frame()
    closed = str(DATA / "calib_closed")
    o21 = b.outdir()
    add(Kind("calibrate -o onto its open frame", ["calibrate", closed, "--open", str(f), "-o", str(f / "intrinsics.json")],
             keep=[f / "intrinsics.json"], source="21"))
    add(Kind("calibrate -o onto its open frame, --force", ["calibrate", closed, "--open", str(f), "-o",
                                                           str(f / "depth.png"), "--force"], keep=[f / "depth.png"],
             source="21"))
    add(Kind("score --heatmap onto the frame's image", ["score", str(f), "--profile", P, "--heatmap",
                                                       str(f / "color.png")], keep=[f / "color.png"], source="21"))
    add(Kind("score -o onto the profile", ["score", str(f), "--profile", P, "-o", P], keep=[Path(P)], source="21"))
    hard = tmp / "hard.png"
    os.link(f / "color.png", hard)
    add(Kind("score --heatmap onto a hard link of the image", ["score", str(f), "--profile", P, "--heatmap", str(hard)],
             keep=[f / "color.png"], source="21"))
    fifo = tmp / "fifo"
    os.mkfifo(fifo)
    add(Kind("calibrate -o onto a FIFO", ["calibrate", closed, "--open", str(f), "-o", str(fifo)], keep=[fifo],
             source="21"))
    add(Kind("calibrate -o onto /dev/full", ["calibrate", closed, "--open", str(f), "-o", "/dev/full", "--force"],
             keep=[Path("/dev/full")], source="21"))
    real, link = tmp / "real.json", tmp / "link.json"
    real.write_text("{}")
    link.symlink_to(real.name)
    add(Kind("calibrate -o onto a symlink", ["calibrate", closed, "--open", str(f), "-o", str(link)], keep=[link, real],
             source="21"))
    add(Kind("calibrate -o onto a folder", ["calibrate", closed, "--open", str(f), "-o", str(o21)], watch=[o21],
             source="21"))
    for field, value in (("depth_scale", 1000), ("depth_scale", 1e-9), ("fx", 1e300), ("fx", 1e-300), ("fy", 1e4),
                         ("ppx", 1e9), ("ppy", -1e6)):
        g = b.frame(**{field: value})
        add(Kind(f"estimate with {field} = {value:g}", ["estimate", str(g), "--profile", P, "--json"],
                 keep=frame_files(g), source="21"))
        o = b.outdir()
        add(Kind(f"calibrate with {field} = {value:g}", ["calibrate", closed, "--open", str(g), "-o", str(o / "x.json")],
                 keep=frame_files(g), watch=[o], source="21"))
    for w, h, what in ((60000, 60000, "a 60000x60000 header"), (20000, 20000, "a 20000x20000 header"),
                       (0, 480, "a zero width")):
        g = b.frame()
        (g / "color.png").write_bytes(png_header(w, h))
        add(Kind(f"estimate, color.png with {what}", ["estimate", str(g), "--profile", P], keep=frame_files(g),
                 source="21"))
    g = b.frame()
    (g / "depth.png").unlink()
    os.mkfifo(g / "depth.png")
    add(Kind("estimate, depth.png is a FIFO", ["estimate", str(g), "--profile", P], source="21"))
    o = b.outdir()
    add(Kind("calibrate --fit CLOSED OPEN (swapped)", ["calibrate", "--fit", str(DATA / "circle_closed"), CIRCLE, "-o",
                                                      str(o / "sw.json")], watch=[o], source="21"))
    o = b.outdir()
    add(Kind("calibrate --n-links 10**6", ["calibrate", closed, "--open", str(f), "--n-links", str(10**6), "-o",
                                           str(o / "n.json")], watch=[o], source="21"))
    bad = b.file("bad.json", "[[1, 2, 3], [4, true, 6]]")
    add(Kind("score --poses with a boolean", ["score", str(f), "--profile", P, "--poses", str(bad)], keep=[bad],
             source="21"))
    huge = b.file("huge.json", json.dumps([[1.0, 2.0, 0.0]] * 5 + [["X", 2.0, 0.0]] + [[1.0, 2.0, 0.0]] * 4)
                  .replace('"X"', "1e400"))
    add(Kind("score --poses with 1e400", ["score", str(f), "--profile", P, "--poses", str(huge)], keep=[huge],
             source="21"))
    o = b.outdir()
    add(Kind("capture --allow-partial with a camera", ["capture", "--out", str(o / "cap"), "--allow-partial"],
             watch=[o], source="21"))

    # -- issue 32: security -----------------------------------------------------------------------
    out.extend(cache_kinds(b, cache))
    for suffix in ("csv", "json"):
        link = b.name("poses").with_suffix(f".{suffix}")
        link.symlink_to(b.shadow)
        add(Kind(f"secret: --poses poses.{suffix} -> shadow (symlink)", ["score", CIRCLE, "--profile", P, "--poses",
                                                                       str(link), *GEOMETRIC],
                 secret=SECRET, source="32"))
    not_json = b.file("p.json", SHADOW_TEXT)
    add(Kind("secret: --profile that is not JSON", ["estimate", CIRCLE, "--profile", str(not_json)], secret=SECRET,
             source="32"))
    link = b.name("profile").with_suffix(".json")
    link.symlink_to(b.shadow)
    add(Kind("secret: --profile p.json -> shadow (symlink)", ["estimate", CIRCLE, "--profile", str(link)],
             secret=SECRET, source="32"))
    g = b.frame()
    (g / "intrinsics.json").write_text(SHADOW_TEXT)
    add(Kind("secret: intrinsics.json is another file", ["estimate", str(g), "--profile", P], secret=SECRET,
             source="32"))
    g = b.frame()
    (g / "intrinsics.json").unlink()
    (g / "intrinsics.json").symlink_to(b.shadow)
    add(Kind("secret: intrinsics.json -> shadow (symlink)", ["estimate", str(g), "--profile", P], secret=SECRET,
             source="32"))
    g = b.frame()
    (g / "color.png").write_text(SHADOW_TEXT)
    add(Kind("secret: color.png is a text file", ["estimate", str(g), "--profile", P], secret=SECRET, source="new"))
    o = b.outdir()
    add(Kind("secret: calibrate --fit --profile shadow", ["calibrate", "--fit", CIRCLE, str(DATA / "circle_closed"),
                                                           "--profile", str(b.shadow), "-o", str(o / "p.json")],
             secret=SECRET, watch=[o], source="new"))
    add(Kind("secret: --poses - with the secret on stdin", ["score", CIRCLE, "--profile", P, "--poses", "-", *GEOMETRIC],
             secret=SECRET, subprocess=True, stdin=SHADOW_TEXT.encode(), source="new"))
    injected = b.frame("calib_open", name="scene\nwarning: INJECTED \x1b[31mred\x1b[0m")
    add(Kind("warning with a newline and escape bytes in the folder name", ["score", str(injected), "--profile", P,
                                                                             GRID, *GEOMETRIC],
             expect="either", source="32"))
    injected2 = b.frame(name="obj\x1b]0;title\x07\rINJECTED")
    add(Kind("estimate, a folder name with OSC/carriage-return bytes", ["estimate", str(injected2), "--profile", P,
                                                                         *GEOMETRIC, "-v"],
             expect="either", source="new"))
    for flag in ("--poses", "--profile"):
        words = (["score", CIRCLE, "--profile", "/dev/zero" if flag == "--profile" else P]
                 + (["--poses", "/dev/zero"] if flag == "--poses" else []) + [*GEOMETRIC])
        add(Kind(f"{flag} /dev/zero", words, subprocess=True, timeout=120, source="32"))
        fifo = b.name("fifo")
        os.mkfifo(fifo)
        words = (["score", CIRCLE, "--profile", str(fifo) if flag == "--profile" else P]
                 + (["--poses", str(fifo)] if flag == "--poses" else []) + [*GEOMETRIC])
        add(Kind(f"{flag} on a FIFO", words, subprocess=True, timeout=30, source="32"))
    sparse = b.name("sparse").with_suffix(".json")
    add(Kind("--profile a 4 GB sparse file", ["estimate", CIRCLE, "--profile", str(sparse)], subprocess=True,
             timeout=120, setup=lambda: os.truncate(sparse.touch() or sparse, 4 * 2**30), source="new"))

    # -- issue 32: silent garbage -----------------------------------------------------------------
    import cv2

    def flip_frame(code):
        g = b.frame()
        for name in ("color.png", "depth.png"):
            image = cv2.imread(str(g / name), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(g / name), cv2.flip(image, code))
        return g

    add(Kind("frame flipped vertically", ["estimate", str(flip_frame(0)), "--profile", P, *GEOMETRIC, "--json"],
             expect="flag", source="32"))
    g = flip_frame(-1)
    data = json.loads((g / "intrinsics.json").read_text())
    data.update(ppx=data["width"] - 1 - data["ppx"], ppy=data["height"] - 1 - data["ppy"])
    (g / "intrinsics.json").write_text(json.dumps(data))
    add(Kind("camera mounted upside down (rotated 180)", ["estimate", str(g), "--profile", P, *GEOMETRIC, "--json"],
             expect="flag", source="32"))
    add(Kind("score on a frame flipped vertically", ["score", str(flip_frame(0)), "--profile", P, GRID, *GEOMETRIC,
                                                     "--json"], expect="flag", source="32"))
    add(Kind("depth_scale 10x (0.001 on a 0.0001 frame), estimate",
             ["estimate", str(b.frame(depth_scale=0.001)), "--profile", P, *GEOMETRIC, "--json"],
             expect="flag", message="depth_scale", source="32"))
    o = b.outdir()
    add(Kind("depth_scale 10x, calibrate", ["calibrate", closed, "--open", str(b.frame(depth_scale=0.001)), "-o",
                                            str(o / "p.json")], watch=[o], message="depth_scale", source="32"))
    add(Kind("fy 800 with fx 430", ["estimate", str(b.frame(fx=430.0, fy=800.0)), "--profile", P, *GEOMETRIC,
                                    "--json"], expect="flag", message="fx|fy", source="32"))
    add(Kind("principal point far outside the image (ppx 1500)", ["estimate", str(b.frame(ppx=1500.0)), "--profile", P,
                                                                    *GEOMETRIC, "--json"],
             expect="flag", message="ppx|principal", source="32"))
    add(Kind("principal point far outside the image (ppy -700)", ["estimate", str(b.frame(ppy=-700.0)), "--profile", P,
                                                                    *GEOMETRIC, "--json"],
             expect="flag", message="ppy|principal", source="32"))
    add(Kind("lens distortion (brown_conrady -0.4, 0.2) ignored",
             ["estimate", str(b.frame(model="brown_conrady", coeffs=[-0.4, 0.2, 0, 0, 0])), "--profile", P, *GEOMETRIC,
              "--json"], expect="ok", check=same_estimate("baseline: estimate"), source="32"))
    add(Kind("lens distortion coefficients 1e30",
             ["estimate", str(b.frame(model="brown_conrady", coeffs=[1e30, 0, 0, 0, 0])), "--profile", P, *GEOMETRIC,
              "--json"], message="coeff|distortion", source="32"))

    def lengths(value):
        def change(data):
            for side in ("left", "right"):
                data["fingers"][side]["length"] = value
        return change

    def other_gripper(data):
        data["gripper"]["base_separation"] *= 1.6
        for side in ("left", "right"):
            data["fingers"][side]["length"] *= 1.6
            data["fingers"][side]["half_thickness"] *= 1.6

    for what, change in (("another gripper's profile (1.6x)", other_gripper), ("finger length 5 mm", lengths(5.0)),
                         ("finger length 100 mm", lengths(100.0)), ("finger length 1e29 mm", lengths(1e29))):
        add(Kind(f"profile: {what}", ["estimate", CIRCLE, "--profile", str(b.profile(change)), *GEOMETRIC, "--json"],
                 expect="flag", message="length|profile", source="32"))
    add(Kind("score with finger length 100 mm (fingers cross)", ["score", CIRCLE, "--profile", str(b.profile(lengths(100.0))),
                                                                  GRID, *GEOMETRIC, "--json"],
             expect="flag", message="length|profile", source="32"))
    degrees = b.file("deg.csv", "x_mm,y_mm,angle_rad\n" + "".join(f"{x},-55,{a}\n" for x in (-3, 0, 3)
                                                                  for a in (-10, 0, 10)))
    add(Kind("poses in degrees (angle 10)", ["score", CIRCLE, "--profile", P, "--poses", str(degrees), *GEOMETRIC,
                                             "--json"], expect="flag", message="angle|degree|radian", source="32"))
    metres = b.file("m.csv", "x_mm,y_mm,angle_rad\n" + "".join(f"{x},{y},0\n" for x in (-0.003, 0, 0.003)
                                                               for y in (-0.06, -0.055, -0.05)))
    add(Kind("poses in metres (0, -0.055, 0)", ["score", CIRCLE, "--profile", P, "--poses", str(metres), *GEOMETRIC,
                                                "--json"], expect="flag", message="metre|mm|unit", source="32"))

    # -- issue 32: crashes and tracebacks -----------------------------------------------------------
    bad_utf8 = b.frame(name=b"scene_\xff\xfe_open")
    o = b.outdir()
    add(Kind("invalid UTF-8 folder name, --overlay-dir", ["estimate", os.fsencode(bad_utf8), "--profile", P, *GEOMETRIC,
                                                          "--json", "--overlay-dir", str(o / "ov")],
             expect="either", watch=[o], subprocess=True, source="32"))
    o = b.outdir()
    add(Kind("invalid UTF-8 folder name, --overlay-dir and -o", ["estimate", os.fsencode(bad_utf8), "--profile", P,
                                                                 *GEOMETRIC, "-o", str(o / "e.json"), "--overlay-dir",
                                                                 str(o)],
             expect="either", watch=[o], subprocess=True, source="32"))
    add(Kind("input path component of 300 characters", ["estimate", str(tmp / ("a" * 300)), "--profile", P],
             message="long|name|no such", source="32"))
    o = b.outdir()
    add(Kind("-o path component of 300 characters", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "-o",
                                                      str(o / ("b" * 300 + ".json"))],
             watch=[o], message="long|name", source="32"))
    umlaut = b.frame(name="kreis_ö_open")
    add(Kind("non-ASCII folder name, ASCII stdout (table)", ["estimate", str(umlaut), "--profile", P, *GEOMETRIC],
             expect="ok", subprocess=True, env={"PYTHONIOENCODING": "ascii"}, source="32"))
    add(Kind("non-ASCII folder name, ASCII stdout (--json)", ["estimate", str(umlaut), "--profile", P, *GEOMETRIC,
                                                              "--json"],
             expect="ok", subprocess=True, env={"PYTHONIOENCODING": "ascii"}, source="32"))
    add(Kind("non-ASCII folder name, ASCII stderr (a refusal)", ["estimate", str(umlaut) + "_missing", "--profile", P],
             subprocess=True, env={"PYTHONIOENCODING": "ascii"}, source="new"))
    o = b.outdir()
    add(Kind("stdout closed, score --json", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "--json"],
             stdout="closed", subprocess=True, watch=[o], source="32"))
    o = b.outdir()
    add(Kind("stdout on a full disk (/dev/full), score --json", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC,
                                                                 "--json"],
             stdout="full", subprocess=True, source="32"))
    o = b.outdir()
    add(Kind("stdout on /dev/full, estimate --json -o out.json", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC,
                                                                  "--json", "-o", str(o / "out.json")],
             stdout="full", expect="either", subprocess=True, watch=[o], source="32"))
    add(Kind("stdout a pipe closed after 100 bytes", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "--json"],
             stdout="head", expect="either", subprocess=True, source="new"))
    o = b.outdir()
    add(Kind("-o on a full disk (file-size limit 64 kB)", ["score", CIRCLE, "--profile", P, *GEOMETRIC, "--top", "0",
                                                           "-o", str(o / "out.json")],
             fsize=64 * 1024, subprocess=True, watch=[o], source="32"))
    for variable, value, expect in (("JAX_DEBUG_NANS", "1", "either"), ("JAX_DEBUG_INFS", "1", "either"),
                                    ("JAX_PLATFORMS", "cuda", "refuse"), ("EQX_ON_ERROR", "raise", "either"),
                                    ("EQX_ON_ERROR", "breakpoint", "either"), ("EQX_ON_ERROR", "bogus", "either")):
        add(Kind(f"{variable}={value}", ["score", CIRCLE, "--profile", P, "--grid=-30:30:3,-90:-40:3,0:0:1", *GEOMETRIC,
                                         "--json"],
                 expect=expect, message=variable if expect == "refuse" else "", subprocess=True, timeout=300,
                 env={variable: value}, source="32"))

    def api(what):
        def call():
            import numpy as np

            import softgrip_jax
            from softgrip_calib.profile import load_profile

            gripper = load_profile(PROFILE).gripper()
            poses = np.zeros((4, 3), np.float32)
            if what == "sdf None":
                softgrip_jax.score(gripper, None, poses, estimator=softgrip_jax.Geometric())
            elif what == "sdf array":
                softgrip_jax.score(gripper, np.zeros((3, 3)), poses, estimator=softgrip_jax.Geometric())
            elif what == "profile dict":
                from softgrip_vision.scene import frame_scene

                frame_scene(DATA / "circle_open", json.loads(Path(PROFILE).read_text()))
            elif what == "poses string":
                sdf = softgrip_jax.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=64)
                softgrip_jax.score(gripper, sdf, "0,0,0", estimator=softgrip_jax.Geometric())
            elif what == "estimate finger None":
                sdf = softgrip_jax.PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=64)
                softgrip_jax.estimate(None, sdf, np.zeros(2), estimator=softgrip_jax.Geometric())
        return call

    for what, source in (("sdf None", "32"), ("sdf array", "32"), ("profile dict", "32"), ("poses string", "new"),
                         ("estimate finger None", "new")):
        add(Kind(f"API: score/estimate with {what}", call=api(what), source=source))
    for sig, name in ((signal.SIGTERM, "SIGTERM"), (signal.SIGTERM, "SIGTERM"), (signal.SIGTERM, "SIGTERM"),
                      (signal.SIGINT, "SIGINT"), (signal.SIGINT, "SIGINT")):
        o = b.outdir()
        delay = round(rng.uniform(2.0, 12.0), 1)
        add(Kind(f"{name} at {delay} s during score --top 0 -o out.json",
                 ["score", CIRCLE, "--profile", P, *GEOMETRIC, "--top", "0", "-o", str(o / "out.json")],
                 expect="signal", send=(sig, delay), subprocess=True, watch=[o], source="32"))
    for sig, name in ((signal.SIGTERM, "SIGTERM"), (signal.SIGINT, "SIGINT")):
        o = b.outdir()
        add(Kind(f"{name} when the temporary file appears, score --top 0 -o out.json",
                 ["score", CIRCLE, "--profile", P, *GEOMETRIC, "--top", "0", "-o", str(o / "out.json")],
                 expect="signal", send=(sig, "tmp"), subprocess=True, watch=[o], source="32"))
    delay = round(rng.uniform(2.0, 10.0), 1)
    add(Kind(f"SIGTERM at {delay} s during estimate --json (stdout)", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC,
                                                                       "--json"],
             expect="signal", send=(signal.SIGTERM, delay), subprocess=True, source="new"))
    add(Kind("calibrate --fit -o into a read-only folder (/sys)", ["calibrate", "--fit", CIRCLE,
                                                                   str(DATA / "circle_closed"), *GEOMETRIC, "-o",
                                                                   "/sys/fitted.json"],
             message="/sys", max_seconds=15.0, source="32"))
    add(Kind("greyscale color.png", ["estimate", str(b.image_frame(lambda im: cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))),
                                     "--profile", P, *GEOMETRIC], message="grey|gray|channel", source="32"))
    rows = "".join(f"{x},{y},0\n" for x in (-3, 0, 3) for y in (-58, -52))
    bom = b.file("bom.csv", "\ufeffx_mm,y_mm,angle_rad\n" + rows)
    add(Kind("CSV saved by Excel as CSV UTF-8 (BOM)", ["score", CIRCLE, "--profile", P, "--poses", str(bom), *GEOMETRIC,
                                                       "--json"], expect="ok", source="32"))
    semi = b.file("semi.csv", "x_mm;y_mm;angle_rad\n" + rows.replace(",", ";"))
    add(Kind("CSV with semicolons", ["score", CIRCLE, "--profile", P, "--poses", str(semi), *GEOMETRIC, "--json"],
             expect="either", message="semicolon", source="32"))

    # -- beyond the issue: a new user's mistakes --------------------------------------------------
    add(Kind("intrinsics for another resolution (1280x720)", ["estimate", str(b.frame(width=1280, height=720)),
                                                               "--profile", P, *GEOMETRIC, "--json"],
             message="1280|720|width|resolution|size"))
    add(Kind("intrinsics with width and height swapped", ["estimate", str(b.frame(width=480, height=640)),
                                                           "--profile", P, *GEOMETRIC, "--json"],
             message="480x640|640x480|width|height|size"))
    add(Kind("depth.png 8-bit", ["estimate", str(b.image_frame(lambda im: (im // 256).astype("uint8"), "depth.png")),
                                 "--profile", P, *GEOMETRIC], message="8-bit|16-bit"))
    add(Kind("colour and depth sizes differ", ["estimate", str(b.image_frame(lambda im: cv2.resize(im, (320, 240)),
                                                                            "depth.png")),
                                               "--profile", P, *GEOMETRIC], message="size|320|differ|match"))
    add(Kind("depth all zeros (no readings)", ["estimate", str(b.image_frame(lambda im: im * 0, "depth.png")),
                                               "--profile", P, *GEOMETRIC], message="depth"))
    add(Kind("colour image all black", ["estimate", str(b.image_frame(lambda im: im * 0)), "--profile", P, *GEOMETRIC],
             expect="flag"))
    g = b.frame()
    depth = cv2.imread(str(g / "depth.png"), cv2.IMREAD_UNCHANGED).astype("float32") * 0.0001
    depth[::2] = float("nan")
    (g / "depth.png").unlink()
    cv2.imwrite(str(g / "depth.tiff"), depth)
    add(Kind("NaN in every other row of depth.tiff", ["estimate", str(g), "--profile", P, *GEOMETRIC, "--json"],
             expect="either"))
    g = b.frame()
    cv2.imwrite(str(g / "depth.tiff"), depth * 0 + 0.5)
    add(Kind("depth.png and depth.tiff both present", ["estimate", str(g), "--profile", P, *GEOMETRIC, "--json"],
             expect="either", message="depth"))
    g = b.frame()
    (g / "color.png").write_bytes((DATA / "circle_open" / "color.png").read_bytes()[:5000])
    add(Kind("color.png truncated", ["estimate", str(g), "--profile", P], message="color.png"))
    g = b.frame()
    (g / "intrinsics.json").write_bytes(b"")
    add(Kind("intrinsics.json empty (0 bytes)", ["estimate", str(g), "--profile", P], message="intrinsics"))
    add(Kind("intrinsics fx as a string", ["estimate", str(b.frame(fx="385")), "--profile", P], message="fx"))
    g = b.frame()
    (g / "intrinsics.json").unlink()
    add(Kind("intrinsics.json missing", ["estimate", str(g), "--profile", P], message="intrinsics"))
    add(Kind("profile from a future schema version (99)", ["estimate", CIRCLE, "--profile",
                                                            str(b.profile(lambda d: d.update(version=99))),
                                                            *GEOMETRIC], message="version"))

    def n_links(value):
        def change(data):
            for side in ("left", "right"):
                data["fingers"][side]["n_links"] = value
        return change

    add(Kind("profile with n_links 0", ["estimate", CIRCLE, "--profile", str(b.profile(n_links(0))), *GEOMETRIC],
             message="n_links"))
    nan_profile = b.file("nan.json", Path(PROFILE).read_text().replace('"theta_entire": 0.5505147957273672',
                                                                       '"theta_entire": NaN'))
    add(Kind("profile with theta_entire NaN", ["estimate", CIRCLE, "--profile", str(nan_profile), *GEOMETRIC],
             message="theta|nan|finite"))
    add(Kind("profile with left and right of different n_links", ["estimate", CIRCLE, "--profile",
                                                                   str(b.profile(lambda d: d["fingers"]["left"]
                                                                                 .update(n_links=7))), *GEOMETRIC,
                                                                   "--json"], expect="either"))
    loop_a, loop_b = b.name("loop").with_suffix(".json"), b.name("loop").with_suffix(".json")
    loop_a.symlink_to(loop_b)
    loop_b.symlink_to(loop_a)
    add(Kind("profile that is a symlink loop", ["estimate", CIRCLE, "--profile", str(loop_a)],
             message="link|loop|profile"))
    add(Kind("profile that is a folder", ["estimate", CIRCLE, "--profile", str(DATA)], message="profile|folder"))
    add(Kind("frame that is a file", ["estimate", PROFILE, "--profile", P], message="folder|frame"))
    unreadable = b.file("u.json", Path(PROFILE).read_text())
    unreadable.chmod(0)
    add(Kind("profile unreadable (chmod 000)", ["estimate", CIRCLE, "--profile", str(unreadable)], message="permission",
             skip="running as root: chmod 000 does not stop reading" if os.geteuid() == 0 else ""))
    header_only = b.file("h.csv", "x_mm,y_mm,angle_rad\n")
    add(Kind("poses CSV with a header only", ["score", CIRCLE, "--profile", P, "--poses", str(header_only), *GEOMETRIC],
             message="no pose|empty|pose"))
    million = b.name("million").with_suffix(".csv")
    add(Kind("poses CSV with 1,000,001 rows", ["score", CIRCLE, "--profile", P, "--poses", str(million), *GEOMETRIC],
             message="1000000|at most", max_seconds=60.0,
             setup=lambda: million.write_text("0,-55,0\n" * 1_000_001)))
    add(Kind("poses CSV with NaN", ["score", CIRCLE, "--profile", P, "--poses", str(b.file("n.csv", "0,-55,nan\n")),
                                    *GEOMETRIC], message="finite|nan"))
    add(Kind("poses JSON rows of 4 numbers", ["score", CIRCLE, "--profile", P, "--poses",
                                              str(b.file("4.json", "[[1, 2, 3, 4]]")), *GEOMETRIC],
             message="x_mm|pose|value|column"))
    add(Kind("poses CSV in UTF-16 (Excel Unicode text)", ["score", CIRCLE, "--profile", P, "--poses",
                                                          str(b.file("u16.csv", ("x_mm,y_mm\n" + rows).encode("utf-16"))),
                                                          *GEOMETRIC, "--json"], expect="either", message="utf|encod"))
    add(Kind("poses CSV with CRLF line ends", ["score", CIRCLE, "--profile", P, "--poses",
                                              str(b.file("crlf.csv", ("x_mm,y_mm,angle_rad\n" + rows)
                                                         .replace("\n", "\r\n"))), *GEOMETRIC, "--json"], expect="ok"))
    add(Kind("poses CSV with decimal commas", ["score", CIRCLE, "--profile", P, "--poses",
                                              str(b.file("dc.csv", "x_mm;y_mm;angle_rad\n0,5;-55,0;0,0\n")),
                                              *GEOMETRIC, "--json"], expect="either", message="comma|decimal"))
    add(Kind("--poses - with empty stdin", ["score", CIRCLE, "--profile", P, "--poses", "-", *GEOMETRIC],
             subprocess=True, stdin=b"", message="pose|empty|stdin"))
    add(Kind("--poses - with binary garbage on stdin", ["score", CIRCLE, "--profile", P, "--poses", "-", *GEOMETRIC],
             subprocess=True, stdin=bytes(range(256)) * 4, message="pose|stdin"))
    for spec in ("0:1:100000,0:1:100000,0:1:100", "0:1:0,-60:-50:3,0:0:1", "nan:1:3,-60:-50:3,0:0:1",
                 "1e308:-1e308:3,-60:-50:3,0:0:1", "0:1:3,-60:-50:3"):
        add(Kind(f"--grid={spec}", ["score", CIRCLE, "--profile", P, f"--grid={spec}", *GEOMETRIC, "--json"],
                 expect="refuse" if not spec.startswith("1e308") else "flag", message="grid"))
    for flag, value in (("--top", "-1"), ("--mu", "nan"), ("--mu", "-1"), ("--robust", "abc"), ("--robust", "1000000000"),
                        ("--pose-sigma", "1,2,3"), ("--mu-spread", "1")):
        add(Kind(f"score {flag} {value}", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, f"{flag}={value}"],
                 message=flag.lstrip("-").split("-")[0], max_seconds=30.0))
    o = b.outdir()
    add(Kind("-o into a folder that does not exist", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "-o",
                                                       str(o / "missing" / "out.json")], watch=[o], message="exist"))
    o = b.outdir()
    add(Kind("--heatmap with an unknown extension", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "--heatmap",
                                                     str(o / "heat.xyz")], watch=[o], message="xyz|format|extension"))
    o = b.outdir()
    poses_file = b.file("p.json", "[[0, -55, 0]]")
    add(Kind("-o onto the --poses file", ["score", CIRCLE, "--profile", P, "--poses", str(poses_file), *GEOMETRIC, "-o",
                                          str(poses_file)], keep=[poses_file], message="input"))
    o = b.outdir()
    add(Kind("-o and --heatmap the same file", ["score", CIRCLE, "--profile", P, GRID, *GEOMETRIC, "-o",
                                                str(o / "x.png"), "--heatmap", str(o / "x.png")], watch=[o]))
    add(Kind("estimate the same frame folder twice", ["estimate", CIRCLE, CIRCLE, "--profile", P, *GEOMETRIC, "--json"],
             expect="either"))
    twin = b.frame()
    add(Kind("estimate two identical frame folders (a copy)", ["estimate", CIRCLE, str(twin), "--profile", P,
                                                                *GEOMETRIC, "--jsonl"], expect="either"))
    o = b.outdir()
    add(Kind("calibrate --fit with a pair given twice", ["calibrate", "--fit", CIRCLE, str(DATA / "circle_closed"),
                                                         CIRCLE, str(DATA / "circle_closed"), *GEOMETRIC, "-o",
                                                         str(o / "p.json")],
             expect="either", watch=[o], message="twice|duplicate|same"))
    o = b.outdir()
    add(Kind("calibrate with the open frame as CLOSED", ["calibrate", str(DATA / "calib_open"), "--open",
                                                         str(DATA / "calib_open"), "-o", str(o / "p.json")],
             watch=[o], message="closed|open|same"))
    add(Kind("estimate on a frame of the closed gripper", ["estimate", str(DATA / "circle_closed"), "--profile", P,
                                                           *GEOMETRIC, "--json"], expect="flag", message="closed|open"))
    sub = b.name("sub")
    sub.mkdir()
    rel = os.path.join("..", os.path.relpath(DATA / "circle_open", tmp))
    add(Kind("relative frame path with ..", ["estimate", rel, "--profile", os.path.relpath(PROFILE, sub), *GEOMETRIC,
                                             "--json"], expect="ok", cwd=sub))
    add(Kind("LC_ALL=C, a non-ASCII folder name", ["estimate", str(umlaut), "--profile", P, *GEOMETRIC, "--json"],
             expect="ok", subprocess=True, env={"LC_ALL": "C", "LANG": "C"}))
    add(Kind("HOME unset", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"], expect="ok", subprocess=True,
             env={"HOME": None, "MPLCONFIGDIR": None}))
    add(Kind("cache folder on a read-only path (/sys)", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"],
             expect="ok", subprocess=True, env={"JAX_COMPILATION_CACHE_DIR": "/sys/softgrip-cache"}, message="cache"))
    add(Kind("cache folder is a regular file", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"],
             expect="ok", subprocess=True, env={"JAX_COMPILATION_CACHE_DIR": PROFILE}, message="cache"))
    add(Kind("SOFTGRIP_JAX_CACHE=maybe", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"], expect="either",
             subprocess=True, env={"SOFTGRIP_JAX_CACHE": "maybe"}))
    add(Kind("XLA_FLAGS with an unknown flag", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"],
             expect="either", subprocess=True, env={"XLA_FLAGS": "--xla_no_such_flag=1"}, message="XLA_FLAGS"))
    add(Kind("JAX_ENABLE_X64=1", ["estimate", CIRCLE, "--profile", P, *GEOMETRIC, "--json"], expect="either",
             subprocess=True, timeout=300, env={"JAX_ENABLE_X64": "1"}))
    return out


# -- the command --------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="softgrip's reliability battery (issues 21 and 32)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--only", metavar="SUBSTRING", help="run only the kinds whose name contains SUBSTRING")
    parser.add_argument("--list", action="store_true", help="list the kinds and exit")
    parser.add_argument("--in-process", action="store_true", help="skip the kinds that need a subprocess (quick)")
    parser.add_argument("--seed", type=int, default=32, help="seed of the signals' random moments (default 32)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="softgrip-battery-") as folder:
        tmp = Path(folder)
        cache = tmp / "cache"
        # One compilation cache for the in-process kinds and every subprocess (set before JAX is imported).
        os.environ["JAX_COMPILATION_CACHE_DIR"] = str(cache)
        os.environ.pop("SOFTGRIP_JAX_CACHE", None)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
        inputs = tmp / "inputs"
        inputs.mkdir()
        selected = kinds(inputs, cache, random.Random(args.seed))
        if args.only:
            keep_baselines = [k for k in selected if k.source == "baseline"]
            chosen = [k for k in selected if args.only.lower() in k.name.lower()]
            # Cache and distortion kinds need the baselines' exported programs and output.
            if any(k.name.startswith("cache:") or k.check for k in chosen):
                chosen = [k for k in keep_baselines if k not in chosen] + chosen
            selected = chosen
        if args.in_process:
            selected = [k for k in selected if not k.subprocess]
        if args.list:
            for kind in selected:
                print(f"{kind.source:<8} {kind.expect:<6} {'sub ' if kind.subprocess else 'in  '} {kind.name}")
            print(f"{len(selected)} kinds")
            return 0
        results, outputs = [], {}
        scratch = tmp / "scratch"
        scratch.mkdir()
        for kind in selected:
            if kind.skip:
                results.append({"kind": kind.name, "source": kind.source, "outcome": "skipped", "problems": [],
                                "exit": None, "seconds": 0.0, "message": kind.skip})
                continue
            try:
                outcome, problems, obs = observe(kind, env, scratch, outputs)
            except Exception as err:  # noqa: BLE001 - the battery's own failure to build an input
                outcome, problems = "wrong outcome", [f"battery: {type(err).__name__}: {err}"]
                obs = Observation(None)
            last = [line for line in obs.stderr.strip().splitlines() if line.strip()]
            message = problems[0] if problems and outcome != "clean" else (last[-1] if last else "")
            results.append({"kind": kind.name, "source": kind.source, "outcome": outcome, "problems": problems,
                            "exit": obs.code, "seconds": round(obs.seconds, 1),
                            "message": message.encode("unicode_escape").decode()[:200]})
            print(f"{outcome:<14} {kind.name}: {results[-1]['message']}", flush=True,
                  file=sys.stderr if args.json else sys.stdout)
    counts = {k: sum(r["outcome"] == k for r in results) for k in OUTCOMES}
    summary = (f"{len(results)} kinds: " + ", ".join(f"{counts[k]} {k}" for k in SIX)
               + f"; also {counts['hang']} hang, {counts['data lost']} data lost, {counts['unsanitised']} unsanitised, "
               f"{counts['wrong outcome']} wrong outcome, {counts['skipped']} skipped; {counts['clean']} clean")
    if args.json:
        print(json.dumps({"kinds": len(results), "counts": counts, "results": results}, indent=1))
    else:
        print(summary)
    return 0 if counts["clean"] + counts["skipped"] == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
