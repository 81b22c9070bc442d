"""The errors live below the JAX core (softgrip_base), re-exported by it; ``softgrip capture``
reports a camera error without importing JAX."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_core_reexports_the_base_errors():
    import softgrip_base
    import softgrip_jax
    from softgrip_jax._errors import SoftgripError

    assert softgrip_jax.SoftgripError is SoftgripError is softgrip_base.SoftgripError


def test_capture_reports_a_camera_error_without_jax(tmp_path):
    code = (
        "import sys\n"
        "from softgrip_cli import main\n"
        f"status = main(['capture', '--out', {str(tmp_path)!r}, '--allow-partial'])\n"
        "print(status, sorted(m for m in ('jax', 'equinox', 'softgrip_jax') if m in sys.modules))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.stdout.strip() == "2 []", run.stdout + run.stderr
    assert "softgrip capture: error: --allow-partial applies to --bag" in run.stderr
    run = subprocess.run([sys.executable, "-c", "import sys, softgrip_base; print('jax' in sys.modules, "
                          "'numpy' in sys.modules, 'cv2' in sys.modules)"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert run.stdout.strip() == "False False False", run.stdout + run.stderr
