"""ament_flake8 style (PEP 8, 99 columns) over the packages, the tests and the lab."""

import os
import subprocess
import sys


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_flake8_clean():
    paths = [os.path.join(ROOT, p) for p in ('ros2_ws/src', 'tests', 'lab')]
    missing = [p for p in paths if not os.path.isdir(p)]
    assert missing == [], f'moved? {missing}'       # a path gone would pass unlinted
    result = subprocess.run(
        [sys.executable, '-m', 'flake8', '--max-line-length', '99', *paths],
        capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
