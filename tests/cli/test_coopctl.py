"""coopctl as a program: building its parser stays light."""

import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_parser_imports_neither_numpy_nor_numba():
    """status, peers and merge-now start fast: the parser loads no map decoding (numpy, numba kernels)."""
    code = (
        "import sys; from coopd.cli import coopctl; coopctl.build_parser(); "
        "print('numba' in sys.modules or 'numpy' in sys.modules)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": ROOT},
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
