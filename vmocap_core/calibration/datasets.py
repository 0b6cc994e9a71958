"""Known-answer calibration data shipped inside public packages (no other downloads).

The Pose2Sim demo (`pose2sim==0.10.49` wheel on PyPI) holds checkerboard images per camera,
4 synchronized videos and a Qualisys reference calibration. The wheel is cached under
`<repo>/models/pose2sim/` (gitignored) or `~/.cache/vmocap/pose2sim/` and only the demo folder
is unpacked; the package itself is never installed."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

POSE2SIM = "pose2sim==0.10.49"
WHEEL = "pose2sim-0.10.49-py3-none-any.whl"
DEMO = "Pose2Sim/Demo_SinglePerson"


def cache_dirs() -> list[Path]:
    repo = Path(__file__).resolve().parents[2]
    return [repo / "models" / "pose2sim", Path.home() / ".cache" / "vmocap" / "pose2sim"]


def pose2sim_demo(fetch: bool = False) -> Path | None:
    """Path of the unpacked Demo_SinglePerson folder, or None when the wheel is not cached
    (with fetch=True: `pip download --no-deps` it into the first writable cache folder)."""
    for d in cache_dirs():
        if (d / DEMO / "calibration" / "Calib.qca.txt").is_file():
            return d / DEMO
        if (d / WHEEL).is_file():
            return _unpack(d)
    if not fetch:
        return None
    for d in cache_dirs():
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", POSE2SIM, "-d", str(d)], check=True)
        return _unpack(d)
    return None


def _unpack(d: Path) -> Path:
    with zipfile.ZipFile(d / WHEEL) as z:
        z.extractall(d, [n for n in z.namelist() if n.startswith(DEMO + "/")])
    return d / DEMO
