#!/usr/bin/env bash
# Create .venv with the pinned dependencies and install vmocap into it (idempotent).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.lock
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
# PCM test photo (messi5.jpg from opencv-doc); needs root, the tests skip without it
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then apt-get install -y -q opencv-doc >/dev/null || echo "setup.sh: opencv-doc not installed (PCM photo test will skip)"; fi
.venv/bin/vmocap models fetch
