#!/usr/bin/env bash
# Test command: sets everything up on first use, then runs the whole suite (ROS-free core and
# rclpy integration tests with nodes as separate processes). Extra arguments go to pytest.
set -eo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
source scripts/setup.sh
exec python -m pytest tests "$@"
