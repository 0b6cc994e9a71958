"""Running one ONNX model on a batch of views with a given number of CPU threads.

Two strategies:
- "views" (default): one single-threaded onnxruntime session, called concurrently on `threads`
  chunks of the batch (onnxruntime releases the GIL). Measured on this shared 2-core CPU for 4
  BlazePose crops: median 88-102 ms vs 160-190 ms for "intra" in the same minutes (load ~4-5),
  because the per-operator synchronization of intra-op threads suffers most when other
  processes take the cores; one view alone still uses intra-op threads (a second session).
- "intra": every batch in one call with onnxruntime's `threads` intra-op threads.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import numpy as np
import onnx
import onnxruntime as ort

from ..errors import ModelError

PARALLEL_MODES = ("views", "intra")
# onnxruntime's WeightBiasQuantization rewrites a float Conv that sits between DequantizeLinear and
# QuantizeLinear into an int8 one with per-tensor weights; the int8 BlazePose keeps such layers in
# float on purpose (depthwise kernels whose channels span 1e-2..5e2 are ruined per-tensor: measured
# heatmap peaks moved by ~11 cells), so that rewrite is off. Float models do not have the pattern.
DISABLED_OPTIMIZERS = ["WeightBiasQuantization"]
DEFAULT_PARALLEL = "views"


def make_session(model: onnx.ModelProto, threads: int, name: object = "model",
                 config: dict[str, str] | None = None) -> ort.InferenceSession:
    """An onnxruntime CPU session with `threads` intra-op threads (`config`: session config
    entries, e.g. selfcheck.INT8_KERNELS)."""
    opts = ort.SessionOptions()
    for key, value in (config or {}).items():
        opts.add_session_config_entry(key, value)
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"],
                                    disabled_optimizers=DISABLED_OPTIMIZERS)
    except Exception as exc:
        raise ModelError(f"{name}: onnxruntime cannot load it ({exc})") from exc


class Runner:
    """`run(outputs, batch)` of a one-input model, batch first."""

    def __init__(self, model: onnx.ModelProto, threads: int, parallel: str = DEFAULT_PARALLEL, name: object = "model",
                 config: dict[str, str] | None = None) -> None:
        if parallel not in PARALLEL_MODES:
            raise ModelError(f"parallel must be one of {PARALLEL_MODES}, got {parallel!r}")
        self.threads = max(1, int(threads))
        self.parallel = parallel
        self.name = name
        self.config = config
        dim0 = model.graph.input[0].type.tensor_type.shape.dim[0]
        self.batched = bool(dim0.dim_param) or dim0.dim_value == 0  # False: static batch of 1
        split = parallel == "views" and self.threads > 1
        self.session = make_session(model, 1 if split else self.threads, name, config)
        self.input_name = self.session.get_inputs()[0].name
        self._model = model if split else None  # for the lazily built single-view session
        self._single = None if split else self.session
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="vmocap-pcm") if split else None

    def _call(self, session: ort.InferenceSession, outputs: list[str], x: np.ndarray) -> list[np.ndarray]:
        return session.run(outputs, {self.input_name: x})

    def run(self, outputs: Sequence[str], x: np.ndarray) -> list[np.ndarray]:
        return self.run_built(outputs, len(x), lambda part: x[part])

    def run_built(self, outputs: Sequence[str], n: int, build: Callable[[slice], np.ndarray]) -> list[np.ndarray]:
        """As `run` for a batch of n views of which `build(part)` makes the slice `part`, in the
        thread that runs it: the crops' warps then run in parallel as well instead of before the
        CNN in the caller's thread."""
        outputs = list(outputs)
        if self.batched and (n == 1 or self._pool is None):  # one call
            if self._single is None:
                self._single = make_session(self._model, self.threads, self.name, self.config)
            return self._call(self._single, outputs, build(slice(0, n)))
        if self.batched:
            bounds = np.linspace(0, n, min(self.threads, n) + 1).round().astype(int)
            parts = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        else:
            parts = [slice(i, i + 1) for i in range(n)]

        def call(part: slice) -> list[np.ndarray]:
            return self._call(self.session, outputs, build(part))

        results = list(self._pool.map(call, parts)) if self._pool is not None else [call(p) for p in parts]
        return [np.concatenate([r[k] for r in results]) for k in range(len(outputs))]
