#!/usr/bin/env bash
# Idempotent set-up: venv with pinned wheels, the ROS-wheel fix, colcon build of ros2_ws.
# Each step runs only when its inputs changed (stamps under .venv/ and ros2_ws/install/).
# Source it (scripts that need the workspace do) or run it; it leaves the environment ready:
# ROS from .venv, the workspace overlay sourced. It leaves the caller's shell options alone.
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$REPO/.venv"
WS="$REPO/ros2_ws"
PYTHON="${TSR_PYTHON:-python3}"

say() { echo "[setup] $*" >&2; }

# The ROS 2 Jazzy wheels are built for CPython 3.11 (cp311): with another version colcon fails
# later on a CMake path. Checked first, on the interpreter the venv has or would be made with.
REQUIRED_PYTHON=3.11
check_python() {
  local python version
  python=$([ -x "$VENV/bin/python" ] && echo "$VENV/bin/python" || echo "$PYTHON")
  version=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
  [ "$version" = "$REQUIRED_PYTHON" ] && return 0
  if [ "$python" = "$VENV/bin/python" ]; then
    say "Python $REQUIRED_PYTHON is required: $VENV has Python ${version:-unknown}; remove" \
        "it and run again with TSR_PYTHON=python$REQUIRED_PYTHON"
  else
    say "Python $REQUIRED_PYTHON is required: $python is ${version:-not found}; install" \
        "python$REQUIRED_PYTHON and run again with TSR_PYTHON=python$REQUIRED_PYTHON"
  fi
  return 1
}

hash_of() { cat "$@" | sha256sum | cut -d' ' -f1; }

install_venv() {
  local want have
  want=$(hash_of "$REPO/requirements.txt" "$REPO/constraints.txt" "$REPO/scripts/setup.sh")
  have=$(cat "$VENV/.tsr-installed" 2>/dev/null || true)
  [ "$want" = "$have" ] && return 0
  say "installing pinned wheels into $VENV (first run: ~2-3 min)"
  # Each step stops the set-up when it fails (set -e does not act inside `if !`), so that a
  # failed install is never stamped as done.
  [ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV" || return 1
  "$VENV/bin/pip" install --quiet --disable-pip-version-check \
    -r "$REPO/requirements.txt" -c "$REPO/constraints.txt" || return 1
  fix_rosidl_py_exports || return 1
  echo "$want" > "$VENV/.tsr-installed"
}

# The wheels' rosidl_generator_py export files name the wheel build machine's include paths
# (docs/ros_from_wheels.md, fix 2): point them at this interpreter's.
fix_rosidl_py_exports() {
  local py_inc np_inc
  py_inc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])') \
    || return 1
  np_inc=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())') || return 1
  sed -i \
    -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#${np_inc}#g" \
    -e "s#/opt/python/cp311-cp311/include/python3.11#${py_inc}#g" \
    "$VENV"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake
}

build_workspace() {
  local want have
  want=$(cd "$WS" && find -L src -type f ! -name '*.pyc' ! -path '*/__pycache__/*' -print0 \
         | sort -z | xargs -0 sha256sum | sha256sum | cut -d' ' -f1)
  have=$(cat "$WS/install/.tsr-built" 2>/dev/null || true)
  [ "$want" = "$have" ] && return 0
  say "colcon build of $WS"
  # A symlink install keeps the file lists of its last build: a data file removed since makes
  # the next build fail, so a failed build is retried once from a clean build tree.
  colcon_build || { say "rebuilding from scratch"; rm -rf "$WS/build" "$WS/install"; \
                    colcon_build; } || { cat "$WS/colcon_build.log" >&2; exit 1; }
  echo "$want" > "$WS/install/.tsr-built"
}

colcon_build() {
  # Fix 1 of docs/ros_from_wheels.md: colcon-ros copies AMENT_PREFIX_PATH into CMAKE_PREFIX_PATH.
  (cd "$WS" && AMENT_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH" \
     "$VENV/bin/colcon" build --symlink-install --event-handlers console_cohesion- \
     --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
     > "$WS/colcon_build.log" 2>&1)
}

if ! check_python; then
  return 1 2>/dev/null || exit 1
fi
if ! (set -eo pipefail; install_venv && build_workspace); then
  say "set-up failed"
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
source "$WS/install/setup.bash"
# The venv is the ROS underlay (what /opt/ros/jazzy is on a stock install): the ament index must
# see it so share/<pkg>/msg files (bag schemas, type hashes) resolve for std_msgs and friends.
export AMENT_PREFIX_PATH="$AMENT_PREFIX_PATH:$VENV"
export PATH="$VENV/bin:$PATH"
