"""What the tests on rendered bodies share: the skip when the renderer is missing and the rig."""

from __future__ import annotations

import ctypes.util
import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CLIP = REPO / "vmocap_core" / "data" / "motions" / "walk.npz"
needs_rendering = pytest.mark.skipif(
    ctypes.util.find_library("OSMesa") is None or importlib.util.find_spec("anny") is None
    or importlib.util.find_spec("pyrender") is None,
    reason="needs libosmesa6, pyrender-maintained and anny==0.6.2 (scripts/setup.sh)")


def half_size_rig():
    """The benchmark rig at half resolution (512x384): rendering and the CNN stay fast."""
    from vmocap_core.apps.render.recording import scale_rig
    from vmocap_core.cameras.rig_file import load_rig

    return scale_rig(load_rig(REPO / "config" / "benchmark_rig.yaml"), 0.5)
