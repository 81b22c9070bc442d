"""What `softgrip capture` imports: its --help, and a camera error (exit 2), in this process.

    python benchmarks/capture_imports.py help
    python benchmarks/capture_imports.py error

Prints the exit status, the number of modules imported, which heavy packages are among them (jax,
equinox, optimistix, cv2, numpy, scipy, pydantic) and the first line of stderr. Run it from the
root of the checkout to measure the checkout (the current folder shadows an installed copy).
"""

import contextlib
import io
import sys
import tempfile

sys.path.insert(0, "")  # the current folder first: a checkout's packages, as `python -c` sees them

case = sys.argv[1] if len(sys.argv) > 1 else "error"
from softgrip_cli import main  # noqa: E402

argv = {"help": ["capture", "--help"],
        "error": ["capture", "--out", tempfile.mkdtemp(), "--allow-partial"]}[case]
out, err = io.StringIO(), io.StringIO()
with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
heavy = [m for m in ("jax", "equinox", "optimistix", "cv2", "numpy", "scipy", "pydantic") if m in sys.modules]
first = (err.getvalue().strip().splitlines() or [""])[0]
print(f"capture {case}: exit {code}, {len(sys.modules)} modules, heavy: {', '.join(heavy) or 'none'}; stderr: {first}")
