#!/usr/bin/env bash
# Build the ROS interface packages of ros/ that have no PyPI wheel (tf2_msgs: TFMessage, for /tf
# and /tf_static; hri_msgs: IdsList, for the ROS4HRI /humans/bodies/tracked) with the rosidl
# generators from PyPI (requirements.lock) and install them into .venv, so that rclpy can
# publish and subscribe those topics. Needs cmake, ninja and a C/C++ compiler; about 10 s a
# package. Idempotent: a package that already imports is skipped.
# Usage: bash scripts/build_ros_msgs.sh [PACKAGE ...]   (default: every package in ros/)
# Without them vmocap still works: /tf and /tf_static are then only written into the recorder's
# MCAP, and vmocap_skeleton runs without the ROS4HRI outputs (docs/ros_outputs.md).
set -euo pipefail
cd "$(dirname "$0")/.."
V=$(cd .venv && pwd -P)
me=build_ros_msgs.sh
if [ $# -gt 0 ]; then
  packages=("$@")
else
  packages=()
  for d in ros/*/package.xml; do packages+=("$(basename "$(dirname "$d")")"); done
fi
todo=()
for pkg in "${packages[@]}"; do
  [ -f "ros/$pkg/package.xml" ] || { echo "$me: no package ros/$pkg" >&2; exit 1; }
  "$V/bin/python" -c "import $pkg.msg" 2>/dev/null || todo+=("$pkg")
done
[ ${#todo[@]} -eq 0 ] && exit 0
for tool in cmake ninja cc c++; do
  command -v "$tool" >/dev/null || { echo "$me: $tool not found (${todo[*]} not built)" >&2; exit 1; }
done
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export AMENT_PREFIX_PATH="$V" PATH="$V/bin:$PATH"
failed=()
for pkg in "${todo[@]}"; do
  build="$work/$pkg"
  if cmake -S "ros/$pkg" -B "$build" -G Ninja -DCMAKE_PREFIX_PATH="$V" -DCMAKE_INSTALL_PREFIX="$V" \
       -DPython3_EXECUTABLE="$V/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >"$work/$pkg.log" 2>&1 \
     && ninja -C "$build" >>"$work/$pkg.log" 2>&1 && cmake --install "$build" >>"$work/$pkg.log" 2>&1 \
     && "$V/bin/python" -c "import $pkg.msg" 2>>"$work/$pkg.log"; then
    echo "$me: $pkg installed into .venv"
  else
    echo "$me: $pkg failed:" >&2
    tail -20 "$work/$pkg.log" >&2
    failed+=("$pkg")
  fi
done
[ ${#failed[@]} -eq 0 ] || { echo "$me: not built: ${failed[*]}" >&2; exit 1; }
