"""Is the int8 landmark model right, and faster, on the CPU this process runs on?

Integer kernels differ between CPUs. x86 CPUs without VNNI (SSE4.1, AVX2, AVX-512 without VNNI)
multiply uint8 activations by int8 weights with instructions that add pairs of products in
saturating 16-bit registers: with 8-bit weights the sums overflow and the heatmaps are noise
(onnxruntime issues 6004, 14642). onnxruntime's `session.x64quantprecision` runs those layers as
uint8 x uint8 instead (exact, but on a VNNI CPU it also replaces the fast kernels). So the choice
is not made from the CPU's name: both models run, where the code runs, on two bundled real crops
(`data/pcm/reference_crops.jpg`, Pose2Sim demo frames). The native kernels are tried first, the
uint8 x uint8 ones only when those fail; the int8 heatmap peaks must stay within the bounds below
of the float ones, and int8 must be at least MIN_SPEEDUP faster, else the float model is used.
The verdict is computed once per process (`verdict`); `vmocap models check` prints it.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ModelError

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "pcm" / "reference_crops.jpg"
CROP = 256
# Peak shift bounds in 64 x 64 map cells (5 x 5-weighted centroids of confident peaks) and the
# largest presence difference: ~1.5-2.5x what the int8 build shows where its kernels are exact
# (0.05 / 0.5 cells), far below what saturated kernels give (~5 / 30 cells, presence off by ~1).
MEDIAN_CELLS, P95_CELLS, PRESENCE = 0.12, 0.75, 0.25
MIN_SPEEDUP = 1.1  # int8 must take <= 1/1.1 of the float time to be worth its small error
TIMING_REPEATS = 5
# part of the kept verdict's key: a new value has every machine check again once (2: verdicts
# kept before it may hold an emulated CPU's timings, see test_pcm_selfcheck.py's qemu test)
VERDICT_VERSION = 2
# the instruction sets that decide which integer kernels onnxruntime runs
# int8 choices in the order tried: name -> (int8 build, i.e. the model file's suffix; session
# config entries for onnxruntime). "u8s8-w7": the build with 7-bit weights (quantize.WEIGHT_GRIDS),
# which the fast uint8 x int8 kernels of CPUs without VNNI compute without saturating (measured on
# an AVX2-only AMD EPYC: as fast as the 8-bit build, 0.75x the float time); "u8u8": exact
# everywhere but no faster than float there.
INT8_KERNELS: dict[str, tuple[str, dict[str, str]]] = {
    "u8s8": ("_int8", {}),
    "u8s8-w7": ("_int8w7", {}),
    "u8u8": ("_int8", {"session.x64quantprecision": "1"}),
}
# Restricts the int8 kernels tried (comma-separated INT8_KERNELS names), e.g. "u8s8-w7" gives a VNNI
# CPU what a CPU without VNNI gets: how CI and developers reproduce the slower class.
KERNELS_ENV = "VMOCAP_INT8_KERNELS"
X86_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16")
ARM_FLAGS = ("asimd", "asimddp", "i8mm")

log = logging.getLogger("vmocap.pcm")


@dataclass(frozen=True)
class CpuInfo:
    arch: str
    model: str
    flags: tuple[str, ...]  # the relevant ones present

    def describe(self) -> str:
        known = X86_FLAGS if self.arch in ("x86_64", "AMD64") else ARM_FLAGS if self.arch in ("aarch64", "arm64") else ()
        missing = [f for f in known if f not in self.flags]
        return f"{self.model} ({self.arch}; {' '.join(self.flags) or 'no listed SIMD flags'}" + (
            f"; without {' '.join(missing)})" if missing else ")")


# numpy's runtime CPU detection (cpuid, i.e. what onnxruntime's kernels see too, also under an
# emulator) for the flags it knows; /proc/cpuinfo for the rest
NUMPY_NAMES = {"avx2": "AVX2", "avx512f": "AVX512F", "avx512_vnni": "AVX512VNNI", "avx512_bf16": "AVX512BF16",
               "asimd": "ASIMD", "asimddp": "ASIMDDP"}


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> CpuInfo:
    """The CPU's architecture, model name and relevant instruction sets (unknown: empty)."""
    arch = platform.machine() or "unknown"
    model, flags = "unknown CPU", set()
    try:
        text = cpuinfo.read_text()
    except OSError:
        text = ""
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key in ("model name", "cpu model") and model == "unknown CPU":
            model = value.strip()
        elif key in ("flags", "features"):
            flags.update(value.split())
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as detected
    except ImportError:
        detected = {}
    for ours, theirs in NUMPY_NAMES.items():
        if theirs in detected:
            flags.discard(ours)
            if detected[theirs]:
                flags.add(ours)
    wanted = X86_FLAGS + ARM_FLAGS
    return CpuInfo(arch, model, tuple(f for f in wanted if f in flags))


def reference_crops() -> np.ndarray:
    """(N, 256, 256, 3) uint8 BGR crops the check runs on."""
    import cv2

    image = cv2.imread(str(REFERENCE))
    if image is None or image.shape[0] != CROP or image.shape[1] % CROP:
        raise ModelError(f"{REFERENCE}: missing or unreadable self-check crops (reinstall vmocap)")
    return np.ascontiguousarray(image.reshape(CROP, -1, CROP, 3).transpose(1, 0, 2, 3))


def peak_centroids(maps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, J, 2) 5 x 5-weighted centroids around each map's argmax (cells) and (V, J) peak values."""
    V, J, h, w = maps.shape
    flat = maps.reshape(V, J, -1)
    y, x = np.divmod(flat.argmax(-1), w)
    pad = np.pad(maps, ((0, 0), (0, 0), (2, 2), (2, 2)))
    d = np.arange(-2, 3)
    yy = (y[..., None, None] + d[:, None] + 2)  # (V, J, 5, 1)
    xx = (x[..., None, None] + d[None, :] + 2)  # (V, J, 1, 5)
    v, j = np.ogrid[:V, :J]
    win = pad[v[..., None, None], j[..., None, None], yy, xx]  # (V, J, 5, 5)
    total = np.maximum(win.sum((-1, -2)), 1e-12)
    cx = (win * (x[..., None, None] + d[None, :])).sum((-1, -2)) / total
    cy = (win * (y[..., None, None] + d[:, None])).sum((-1, -2)) / total
    return np.stack([cx, cy], -1), flat.max(-1)


@dataclass(frozen=True)
class Agreement:
    """How far the int8 heatmaps are from the float ones on the same crops."""

    median_cells: float
    p95_cells: float
    max_cells: float
    presence_diff: float
    peaks: int
    visibility_diff: float = 0.0  # the landmarks' visibility (weighs the maps: model.py), same bound as presence

    @property
    def ok(self) -> bool:
        return (self.median_cells <= MEDIAN_CELLS and self.p95_cells <= P95_CELLS and self.presence_diff <= PRESENCE
                and self.visibility_diff <= PRESENCE)

    def describe(self) -> str:
        return (f"peaks moved {self.median_cells:.3f} cells median (bound {MEDIAN_CELLS}), {self.p95_cells:.3f} p95 "
                f"(bound {P95_CELLS}), presence by up to {self.presence_diff:.3f}, visibility by up to "
                f"{self.visibility_diff:.3f} (bound {PRESENCE} each) on {self.peaks} peaks")


def agreement(ref: tuple[np.ndarray | None, ...], test: tuple[np.ndarray | None, ...], channels: np.ndarray) -> Agreement:
    """Compare (maps (V, J, h, w), presence (V,)[, visibility (V, J)]) of a model with those of the
    reference model; only the peaks the reference is confident about (> 0.5) on `channels` count."""
    ca, va = peak_centroids(ref[0])
    cb, _ = peak_centroids(test[0])
    confident = (va > 0.5) & np.asarray(channels, bool)[None]
    shift = np.linalg.norm(cb - ca, axis=-1)[confident]
    if shift.size == 0:
        raise ModelError("self-check: the float model sees no confident keypoint on the reference crops")
    dp = float(np.abs(np.asarray(ref[1]) - np.asarray(test[1])).max())
    vis = [x[2] if len(x) > 2 else None for x in (ref, test)]
    dv = 0.0 if vis[0] is None or vis[1] is None else float(np.abs(vis[0] - vis[1])[:, np.asarray(channels, bool)].max())
    return Agreement(float(np.median(shift)), float(np.percentile(shift, 95)), float(shift.max()), dp, int(shift.size), dv)


@dataclass(frozen=True)
class CheckResult:
    cpu: CpuInfo
    onnxruntime: str
    precision: str  # chosen: "int8" or "float"
    reason: str
    int8_kernels: str | None  # the INT8_KERNELS entry that computes correctly here (None: none)
    tried: dict[str, Agreement] = field(default_factory=dict)  # kernels tried -> agreement
    ms_per_crop: dict[str, float] = field(default_factory=dict)  # "float", "int8" (1 thread)

    @property
    def int8_correct(self) -> bool:
        return self.int8_kernels is not None

    @property
    def session_config(self) -> dict[str, str]:
        return dict(INT8_KERNELS[self.int8_kernels][1]) if self.int8_kernels else {}

    @property
    def int8_build(self) -> str:
        """The suffix of the int8 model file that computes correctly here ("_int8" if none does)."""
        return INT8_KERNELS[self.int8_kernels][0] if self.int8_kernels else "_int8"

    @property
    def warning(self) -> str | None:
        """One line for the log when int8 is unusable here (None when it is fine or merely slower)."""
        if self.int8_correct:
            return None
        return (f"the int8 CNN is not usable on this CPU, {self.cpu.describe()}: {self.reason}; "
                "using the float model (`vmocap models check` for details)")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cpu"]["describe"] = self.cpu.describe()
        for k, a in self.tried.items():
            d["tried"][k]["ok"] = a.ok
        d["int8_correct"] = self.int8_correct
        return d


def _time_batch(model, batch: np.ndarray) -> float:
    t0 = time.perf_counter()
    model.run(batch)
    return time.perf_counter() - t0


def allowed_kernels() -> tuple[str, ...]:
    """The INT8_KERNELS entries the check may try: all, or those named in $VMOCAP_INT8_KERNELS."""
    import os

    raw = os.environ.get(KERNELS_ENV, "").strip()
    if not raw:
        return tuple(INT8_KERNELS)
    names = tuple(k.strip() for k in raw.split(",") if k.strip())
    unknown = [k for k in names if k not in INT8_KERNELS]
    if unknown:
        raise ModelError(f"{KERNELS_ENV}: unknown int8 kernels {unknown} (known: {', '.join(INT8_KERNELS)})")
    return names


def run_check(variant: str = "full", repeats: int = TIMING_REPEATS, kernels: tuple[str, ...] | None = None) -> CheckResult:
    """Run float and int8 (each of the INT8_KERNELS `kernels` in turn until one agrees; default
    `allowed_kernels()`) on the reference crops, one thread each, and time the float and the
    correct int8 model (minimum of `repeats` interleaved runs)."""
    import onnxruntime as ort

    from . import fetch
    from .blazepose_net import BlazePoseNet

    cpu = cpu_info()
    batch = reference_crops()
    flt = BlazePoseNet(fetch.model_path(f"pose_landmark_{variant}"), threads=1, variant=variant, precision="float",
                       input_size=CROP)
    def outputs(model: BlazePoseNet) -> tuple[np.ndarray | None, ...]:
        out = model.run(batch)
        return (*model.decode(out), model.visibility(out))

    ref = outputs(flt)

    def result(precision: str, reason: str, used: str | None = None, ms: dict | None = None) -> CheckResult:
        ms = ms or {"float": _time_batch(flt, batch) * 1e3 / len(batch)}
        return CheckResult(cpu, ort.__version__, precision, reason, used, tried, ms)

    tried: dict[str, Agreement] = {}
    missing: list[str] = []
    q = None
    for name in kernels if kernels is not None else allowed_kernels():
        suffix, config = INT8_KERNELS[name]
        try:
            int8_path = fetch.model_path(f"pose_landmark_{variant}{suffix}")
        except ModelError as exc:
            missing.append(f"no int8 model for {name} ({exc})")
            continue
        q = BlazePoseNet(int8_path, threads=1, variant=variant, precision="int8", session_config=config,
                         input_size=CROP)
        tried[name] = agreement(ref, outputs(q), flt.channel_valid)
        if tried[name].ok:
            break
    used = next((k for k, a in tried.items() if a.ok), None)
    if used is None or q is None:
        return result("float", "; ".join([f"{k} kernels: {a.describe()}" for k, a in tried.items()] + missing))
    times: dict[str, list[float]] = {"float": [], "int8": []}
    for _ in range(max(1, repeats)):
        times["float"].append(_time_batch(flt, batch))
        times["int8"].append(_time_batch(q, batch))
    ms = {k: min(v) * 1e3 / len(batch) for k, v in times.items()}
    speedup = ms["float"] / max(ms["int8"], 1e-9)
    figures = f"{ms['int8']:.1f} vs {ms['float']:.1f} ms per crop with {used} kernels"
    if speedup < MIN_SPEEDUP:
        return result("float", f"int8 is correct but not faster here ({figures})", used, ms)
    return result("int8", f"int8 is correct and {speedup:.2f}x faster ({figures})", used, ms)


_verdicts: dict[str, CheckResult] = {}
_lock = threading.Lock()


def from_dict(d: dict) -> CheckResult:
    """The CheckResult that `to_dict` wrote."""
    cpu = CpuInfo(d["cpu"]["arch"], d["cpu"]["model"], tuple(d["cpu"]["flags"]))
    fields = ("median_cells", "p95_cells", "max_cells", "presence_diff", "peaks", "visibility_diff")
    tried = {k: Agreement(**{f: a[f] for f in fields if f in a}) for k, a in d["tried"].items()}
    return CheckResult(cpu, d["onnxruntime"], d["precision"], d["reason"], d["int8_kernels"], tried,
                       {k: float(v) for k, v in d["ms_per_crop"].items()})


def verdict_path(variant: str = "full") -> Path:
    """Where this machine's verdict is kept: one file per CPU (model and flags), onnxruntime
    version, model files (their checksums) and allowed kernels, in the model cache."""
    import hashlib

    import onnxruntime as ort

    from . import fetch

    cpu = cpu_info()
    files = fetch.read_manifest(fetch.model_dir()).get("files", {})
    models = sorted((k, str(v)) for k, v in files.items() if str(k).startswith(f"pose_landmark_{variant}"))
    key = json.dumps([cpu.arch, cpu.model, list(cpu.flags), ort.__version__, models, list(allowed_kernels()),
                      VERDICT_VERSION])
    return fetch.model_dir() / f"selfcheck_{variant}_{hashlib.sha256(key.encode()).hexdigest()[:16]}.json"


def save_verdict(result: CheckResult, variant: str = "full") -> None:
    from ..files import write_text

    write_text(verdict_path(variant), json.dumps(result.to_dict(), indent=1), overwrite=True)


def verdict(variant: str = "full") -> CheckResult:
    """The check's verdict, once per machine: read from the model cache when this CPU,
    onnxruntime and model files were checked before, else `run_check` and kept there. Every
    process on the machine then runs the same precision (int8's speed margin over float can
    be small enough for a timing under load to decide otherwise in one process, which would
    make the graph's results differ from `vmocap process`'s). `vmocap models check` runs it
    again and replaces the kept verdict. Logs one warning when int8 is unusable."""
    with _lock:
        if variant not in _verdicts:
            path = verdict_path(variant)
            try:
                result = from_dict(json.loads(path.read_text()))
            except (OSError, ValueError, KeyError, TypeError):
                result = run_check(variant)
                try:
                    save_verdict(result, variant)
                except OSError as exc:  # a read-only model cache: checked again by the next process
                    log.info("vmocap: self-check verdict not kept (%s)", exc)
            if result.warning:
                log.warning("vmocap: %s", result.warning)
            _verdicts[variant] = result
        return _verdicts[variant]


def last_verdict(variant: str = "full") -> CheckResult | None:
    """The verdict this process reached, if a model asked for one."""
    return _verdicts.get(variant)


# ---------------------------------------------------------------------- `vmocap models check`
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--variant", default="full", choices=("full",), help="landmark model with an int8 build")
    parser.add_argument("--repeats", type=int, default=TIMING_REPEATS, help="timing runs per precision (minimum taken)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    try:
        result = run_check(args.variant, args.repeats)
    except ModelError as exc:
        print(f"vmocap models check: {exc}")
        return 1
    try:
        save_verdict(result, args.variant)  # what every vmocap process on this machine uses from now on
    except OSError as exc:
        print(f"vmocap models check: verdict not kept ({exc})")
    if args.json:
        print(json.dumps(result.to_dict(), indent=1))
        return 0
    print(f"CPU:          {result.cpu.describe()}")
    print(f"onnxruntime:  {result.onnxruntime}")
    for name, a in result.tried.items():
        print(f"{'int8 ' + name + ':':<14}{'PASS' if a.ok else 'FAIL'}: {a.describe()}, max {a.max_cells:.2f} cells")
    if not result.tried:
        print("int8 check:   not run (no int8 model)")
    print("time per crop (1 thread): " + ", ".join(f"{k} {v:.2f} ms" for k, v in result.ms_per_crop.items()))
    print(f"precision:    {result.precision} ({result.reason})")
    if result.warning:
        print(f"WARNING: {result.warning}")
    return 0
