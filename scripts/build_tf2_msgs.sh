#!/usr/bin/env bash
# Build the tf2_msgs interface (TFMessage only, ros/tf2_msgs) with the rosidl generators from
# PyPI (requirements.lock) and install it into .venv, so that rclpy can publish and subscribe
# /tf and /tf_static. Needs cmake, ninja and a C/C++ compiler; about 10 s. Idempotent: does
# nothing when tf2_msgs already imports. Without it vmocap still works: /tf and /tf_static are
# then only written into the recorder's MCAP (see docs/ros_outputs.md).
set -euo pipefail
cd "$(dirname "$0")/.."
V=$(cd .venv && pwd -P)
if "$V/bin/python" -c "import tf2_msgs.msg" 2>/dev/null; then
  exit 0
fi
for tool in cmake ninja cc c++; do
  command -v "$tool" >/dev/null || { echo "build_tf2_msgs.sh: $tool not found" >&2; exit 1; }
done
build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
export AMENT_PREFIX_PATH="$V" PATH="$V/bin:$PATH"
cmake -S ros/tf2_msgs -B "$build" -G Ninja -DCMAKE_PREFIX_PATH="$V" -DCMAKE_INSTALL_PREFIX="$V" \
  -DPython3_EXECUTABLE="$V/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >"$build/cmake.log" 2>&1 \
  || { tail -20 "$build/cmake.log" >&2; exit 1; }
ninja -C "$build" >"$build/build.log" 2>&1 || { tail -20 "$build/build.log" >&2; exit 1; }
cmake --install "$build" >/dev/null
"$V/bin/python" -c "import tf2_msgs.msg; print('build_tf2_msgs.sh: tf2_msgs installed into .venv')"
