#!/usr/bin/env bash
# Test command: sets everything up on first use, then runs pytest: with no arguments the whole
# suite (ROS-free core and rclpy integration tests with nodes as separate processes); arguments
# replace that, e.g. `scripts/test.sh -m "not ros"` (the core alone) or a test file.
set -eo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/setup.sh
exec python -m pytest "$@"
