"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8 and PyGObject.

Optional: Aravis is imported only when a camera is opened; without it a SourceError says
what to install (Debian `gir1.2-aravis-0.8`, pip `PyGObject<3.51`; scripts/setup.sh does
both where it can). Discovery is confined to the interfaces named in `setup_interfaces`
(GigE Vision broadcasts on every network interface: tests use only the in-process 'Fake').

Configuration: pixel format (delivered as BGR or mono8), exposure (us), gain (dB), frame
rate, trigger mode ('free' running, 'software', or a hardware line such as 'Line0'), region,
buffer pool size. Counters: completed / incomplete / dropped buffers (frame id gaps and
stream underruns). Stamps: the camera's timestamp mapped to ROS time by a ClockMapper fed
with the host time at which Aravis received each buffer. A lost camera (the device's
'control-lost' signal, or a failed feature access) makes `read` raise SourceError; a
SourceRig reopens it when it comes back.
"""

from __future__ import annotations

import threading
from typing import Any

import cv2
import numpy as np

from ..errors import SourceError
from .base import Frame, FrameSource
from .clock import ClockMapper

INSTALL_HINT = ("Aravis is not available: install the Debian packages gir1.2-aravis-0.8 libgirepository1.0-dev "
                "libcairo2-dev pkg-config and `pip install PyGObject==3.50.0` (scripts/setup.sh does this as root)")
ALL_INTERFACES = ("Fake", "GigEVision", "USB3Vision")

# GenICam Bayer names give the colour of pixel (0, 0); OpenCV names that of pixel (1, 1).
_BAYER = {"BayerRG8": cv2.COLOR_BayerBG2BGR, "BayerBG8": cv2.COLOR_BayerRG2BGR,
          "BayerGR8": cv2.COLOR_BayerGB2BGR, "BayerGB8": cv2.COLOR_BayerGR2BGR}
_lock = threading.Lock()
_configured: tuple[str, ...] | None = None


def aravis_module() -> Any:
    """The Aravis GObject module, or SourceError when it is not installed."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # type: ignore
    except (ImportError, ValueError) as exc:
        raise SourceError(f"{INSTALL_HINT} ({exc})") from None
    return Aravis


def available() -> bool:
    try:
        aravis_module()
        return True
    except SourceError:
        return False


def setup_interfaces(enabled: tuple[str, ...] = ("GigEVision", "USB3Vision")) -> Any:
    """Enable exactly `enabled` among Aravis' interfaces (process-wide), before any device
    list update, so discovery never probes an interface that was not asked for."""
    global _configured
    Ar = aravis_module()
    with _lock:
        for name in ALL_INTERFACES:
            if name not in enabled:
                Ar.disable_interface(name)
        for name in enabled:
            Ar.enable_interface(name)
        _configured = tuple(enabled)
    return Ar


def list_cameras(enabled: tuple[str, ...] | None = None) -> list[str]:
    Ar = setup_interfaces(enabled or _configured or ("GigEVision", "USB3Vision"))
    Ar.update_device_list()
    return [Ar.get_device_id(i) for i in range(Ar.get_n_devices())]


def to_image(data: np.ndarray, width: int, height: int, fmt: str, mono: bool) -> np.ndarray:
    """A raw GenICam buffer -> (H, W, 3) BGR or (H, W) mono uint8."""
    try:
        if fmt in ("Mono8",) or fmt in _BAYER:
            raw = data[: width * height].reshape(height, width)
            if fmt == "Mono8":
                return raw.copy() if mono else cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR)
            bgr = cv2.cvtColor(raw, _BAYER[fmt])
        elif fmt in ("Mono10", "Mono12", "Mono14", "Mono16"):
            bits = int(fmt[4:])
            raw = data[: 2 * width * height].view("<u2").reshape(height, width)
            m8 = (raw >> (bits - 8)).astype(np.uint8)
            return m8 if mono else cv2.cvtColor(m8, cv2.COLOR_GRAY2BGR)
        elif fmt in ("RGB8", "RGB8Packed"):
            bgr = cv2.cvtColor(data[: 3 * width * height].reshape(height, width, 3), cv2.COLOR_RGB2BGR)
        elif fmt in ("BGR8", "BGR8Packed"):
            bgr = data[: 3 * width * height].reshape(height, width, 3).copy()
        elif fmt in ("YUV422_8", "YUV422_8_UYVY", "YUV422Packed"):
            bgr = cv2.cvtColor(data[: 2 * width * height].reshape(height, width, 2), cv2.COLOR_YUV2BGR_UYVY)
        elif fmt == "YUV422_YUYV_Packed":
            bgr = cv2.cvtColor(data[: 2 * width * height].reshape(height, width, 2), cv2.COLOR_YUV2BGR_YUY2)
        else:
            raise SourceError(f"pixel format {fmt} is not supported (Mono8/10/12/14/16, Bayer*8, RGB8, BGR8, YUV422)")
    except ValueError as exc:
        raise SourceError(f"buffer of {data.size} bytes does not hold a {width}x{height} {fmt} image ({exc})") from None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if mono else bgr


class AravisFrameSource(FrameSource):
    """One GenICam camera. `camera_id` is Aravis' device id (e.g. 'Fake_1', a serial, an
    IP address); None opens the first camera found."""

    live = True

    def __init__(self, camera_id: str | None = None, name: str | None = None, pixel_format: str | None = None,
                 mono: bool = False, exposure_us: float | None = None, gain_db: float | None = None,
                 fps: float | None = None, trigger: str = "free", trigger_activation: str | None = None,
                 buffers: int = 8, region: tuple[int, int, int, int] | None = None,
                 interfaces: tuple[str, ...] | None = None) -> None:
        self.camera_id = camera_id
        self.name = name or camera_id or "aravis"
        self.pixel_format = pixel_format
        self.mono = mono
        self.exposure_us, self.gain_db, self.fps = exposure_us, gain_db, fps
        if trigger not in ("free", "software") and not trigger.startswith("Line"):
            raise SourceError(f"camera {self.name}: trigger must be 'free', 'software' or a line like 'Line0', not '{trigger}'")
        self.trigger_mode = trigger
        self.software_trigger = trigger == "software"
        self.trigger_activation = trigger_activation
        if buffers < 2:
            raise SourceError(f"camera {self.name}: the buffer pool needs at least 2 buffers, not {buffers}")
        self.buffers = int(buffers)
        self.region = region
        self.interfaces = interfaces
        self.clock = ClockMapper()
        self._cam: Any = None
        self._stream: Any = None
        self._lost = threading.Event()
        self._size: tuple[int, int] | None = None
        self._last_frame_id: int | None = None
        self._counts = {"frames": 0, "incomplete": 0, "dropped": 0, "timeouts": 0}
        self._underruns0 = 0
        self.settings: dict[str, Any] = {}

    # ------------------------------------------------------------------ open / close
    def open(self) -> None:
        Ar = setup_interfaces(self.interfaces) if self.interfaces else (
            aravis_module() if _configured else setup_interfaces())
        from gi.repository import GLib  # type: ignore

        try:
            cam = Ar.Camera.new(self.camera_id)
        except GLib.Error as exc:
            raise SourceError(f"camera {self.name}: cannot open Aravis device {self.camera_id or '(first)'}: {exc.message}") from None
        if cam is None:
            raise SourceError(f"camera {self.name}: Aravis device {self.camera_id or '(first)'} not found")
        self._cam = cam
        self._lost.clear()
        try:
            self._configure(Ar)
            cam.get_device().connect("control-lost", lambda *_: self._lost.set())
            stream = cam.create_stream(None, None)
            if stream is None:
                raise SourceError(f"camera {self.name}: cannot create a stream")
            payload = cam.get_payload()
            for _ in range(self.buffers):
                stream.push_buffer(Ar.Buffer.new_allocate(payload))
            self._stream = stream
            self._underruns0 = self._stream_stats()[2]
            cam.set_acquisition_mode(Ar.AcquisitionMode.CONTINUOUS)
            cam.start_acquisition()
        except GLib.Error as exc:
            self.close()
            raise SourceError(f"camera {self.name}: configuration failed: {exc.message}") from None
        self.clock.reset()
        self._last_frame_id = None

    def _configure(self, Ar: Any) -> None:
        cam = self._cam
        if self.region is not None:
            cam.set_region(*[int(v) for v in self.region])
        if self.pixel_format:
            avail = list(cam.dup_available_pixel_formats_as_strings() or [])
            if avail and self.pixel_format not in avail:
                raise SourceError(f"camera {self.name}: pixel format {self.pixel_format} not offered (has {avail})")
            cam.set_pixel_format_from_string(self.pixel_format)
        if self.exposure_us is not None:
            lo, hi = cam.get_exposure_time_bounds()
            if not lo <= self.exposure_us <= hi:
                raise SourceError(f"camera {self.name}: exposure {self.exposure_us} us outside [{lo}, {hi}]")
            cam.set_exposure_time_auto(Ar.Auto.OFF) if cam.is_exposure_auto_available() else None
            cam.set_exposure_time(float(self.exposure_us))
        if self.gain_db is not None:
            if not cam.is_gain_available():
                raise SourceError(f"camera {self.name}: gain is not adjustable")
            lo, hi = cam.get_gain_bounds()
            if not lo <= self.gain_db <= hi:
                raise SourceError(f"camera {self.name}: gain {self.gain_db} dB outside [{lo}, {hi}]")
            cam.set_gain_auto(Ar.Auto.OFF) if cam.is_gain_auto_available() else None
            cam.set_gain(float(self.gain_db))
        if self.trigger_mode == "free":
            cam.clear_triggers()
            if self.fps is not None:
                cam.set_frame_rate(float(self.fps))
        else:
            source = "Software" if self.trigger_mode == "software" else self.trigger_mode
            sources = list(cam.dup_available_trigger_sources() or [])
            if sources and source not in sources:
                raise SourceError(f"camera {self.name}: trigger source {source} not offered (has {sources})")
            cam.set_trigger(source)
            if self.trigger_activation:
                cam.set_string("TriggerActivation", self.trigger_activation)
        x, y, w, h = cam.get_region()
        self._size = (int(w), int(h))
        self.settings = {
            "model": f"{cam.get_vendor_name()} {cam.get_model_name()}", "pixel_format": cam.get_pixel_format_as_string(),
            "width": int(w), "height": int(h), "exposure_us": cam.get_exposure_time() if cam.is_exposure_time_available() else None,
            "gain_db": cam.get_gain() if cam.is_gain_available() else None,
            "fps": cam.get_frame_rate() if cam.is_frame_rate_available() else None,
            "trigger": self.trigger_mode, "buffers": self.buffers,
        }

    def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                cam.stop_acquisition()
            except Exception:  # noqa: BLE001 - a lost camera cannot be stopped; release anyway
                pass
        self._stream = None

    @property
    def size(self) -> tuple[int, int] | None:
        return self._size

    # ------------------------------------------------------------------ acquisition
    def trigger(self) -> None:
        if not self.software_trigger:
            raise SourceError(f"camera {self.name}: trigger mode is '{self.trigger_mode}', not 'software'")
        if self._cam is None:
            raise SourceError(f"camera {self.name}: trigger before open")
        from gi.repository import GLib  # type: ignore

        try:
            self._cam.software_trigger()
        except GLib.Error as exc:
            self._lost.set()
            raise SourceError(f"camera {self.name}: software trigger failed: {exc.message}") from None

    def _stream_stats(self) -> tuple[int, int, int]:
        try:
            vals = [int(v) for v in (self._stream.get_statistics() or ())]  # completed, failures, underruns
        except Exception:  # noqa: BLE001 - statistics are diagnostics only
            vals = []
        return tuple((vals + [0, 0, 0])[:3])  # type: ignore[return-value]

    def read(self, timeout: float = 1.0) -> Frame | None:
        if self._lost.is_set():
            self.close()
            raise SourceError(f"camera {self.name}: connection lost")
        if self._stream is None:
            raise SourceError(f"camera {self.name}: read before open")
        Ar = aravis_module()
        buf = self._stream.timeout_pop_buffer(int(timeout * 1e6))
        if buf is None:
            self._counts["timeouts"] += 1
            if self._lost.is_set():
                self.close()
                raise SourceError(f"camera {self.name}: connection lost")
            return None
        try:
            if buf.get_status() != Ar.BufferStatus.SUCCESS:
                self._counts["incomplete"] += 1
                return None
            frame_id = int(buf.get_frame_id())
            if self._last_frame_id is not None and frame_id > self._last_frame_id + 1:
                self._counts["dropped"] += frame_id - self._last_frame_id - 1
            self._last_frame_id = frame_id
            w, h = int(buf.get_image_width()), int(buf.get_image_height())
            # the format read once at configuration: a feature read per frame costs a GigE round trip
            data = np.frombuffer(buf.get_data(), dtype=np.uint8)
            img = to_image(data, w, h, self.settings["pixel_format"], self.mono)
            dev_ns, host_ns = int(buf.get_timestamp()), int(buf.get_system_timestamp())
            stamp = self.clock.update(dev_ns, host_ns) if dev_ns > 0 else host_ns
        finally:
            self._stream.push_buffer(buf)  # back to the pool
        self._counts["frames"] += 1
        return Frame(self.name, stamp, img, seq=frame_id)

    def stats(self) -> dict[str, int | float]:
        completed, failures, underruns = self._stream_stats() if self._stream is not None else (0, 0, self._underruns0)
        return {**self._counts, "stream_completed": completed, "stream_failures": failures,
                "stream_underruns": underruns - self._underruns0,
                "clock_offset_ms": self.clock.offset_ns * 1e-6, "clock_drift_ppm": self.clock.drift_ppm}
