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
# Aravis (GenICam cameras, optional): system typelib + PyGObject built against the system glib.
# Root only; vmocap works without it (the Aravis source reports what is missing, its tests skip).
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  if DEBIAN_FRONTEND=noninteractive apt-get install -y -q gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config >/dev/null; then
    .venv/bin/python -m pip install -q --disable-pip-version-check "PyGObject==3.50.0" "pycairo==1.29.2" \
      || echo "setup.sh: PyGObject not built (Aravis source unavailable)"
  else
    echo "setup.sh: Aravis packages not installed (Aravis source unavailable)"
  fi
fi
.venv/bin/vmocap models fetch
