"""ament_flake8 style (PEP 8, 99 columns) over the packages, tests and benchmarks."""

import os
import subprocess
import sys


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_flake8_clean():
    paths = [os.path.join(ROOT, p) for p in ('ros2_ws/src', 'tests', 'bench')]
    result = subprocess.run(
        [sys.executable, '-m', 'flake8', '--max-line-length', '99',
         *[p for p in paths if os.path.isdir(p)]], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
