"""Process settings applied on ``import ggfslam`` (``ggfslam/numba_setup.py``): OpenMP spinning, numba's cache."""
import os
import subprocess
import sys

import pytest

from ggfslam import numba_setup

PROBE = "import os, ggfslam; print(os.environ.get('GOMP_SPINCOUNT', '-'), os.environ.get('OMP_WAIT_POLICY', '-'))"


def _run(code: str, env_extra: dict[str, str] | None = None) -> str:
    """Standard output of ``python -c code`` in an environment without the user's OpenMP wait settings."""
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout


@pytest.mark.parametrize("env_extra, expected", [
    ({}, [numba_setup.GOMP_SPINCOUNT, "-"]),  # unset: short spinning
    ({"GOMP_SPINCOUNT": "250"}, ["250", "-"]),  # the user's value wins
    ({"OMP_WAIT_POLICY": "PASSIVE"}, ["-", "PASSIVE"]),  # a wait policy of the user's: spinning left to it
])
def test_openmp_spinning_set_on_import_unless_the_user_chose(env_extra, expected):
    assert _run(PROBE, env_extra).split() == expected


def test_torch_imported_after_ggfslam_reads_the_setting():
    """torch's bundled libgomp reads GOMP_SPINCOUNT when it loads: the package sets it before anything imports
    torch (ggfslam/__init__.py imports nothing else first)."""
    code = ("import sys, ggfslam; assert 'torch' not in sys.modules, 'ggfslam imported torch on import'; "
            "import os; print(os.environ['GOMP_SPINCOUNT'])")
    assert _run(code).strip() == numba_setup.GOMP_SPINCOUNT
