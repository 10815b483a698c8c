"""`aravis://ADDRESS-OR-ID`: GigE Vision and USB3 Vision cameras through Aravis 0.8 (PyGObject).

Settings go through the GenICam SFNC features (TriggerSelector/TriggerMode/TriggerSource/
TriggerActivation, ExposureTime or ExposureTimeAbs, Gain or GainRaw, AcquisitionFrameRate,
PixelFormat), falling back to the older names that many GigE cameras still use.

Frames come from a pool of pre-allocated buffers that the stream thread fills; each popped buffer
is decoded into a Frame (one copy) and pushed straight back. Missing frame ids are counted as
drops; buffers that arrive damaged are counted as incomplete; a pop that times out probes the
device, so a camera that vanished is reported as disconnected rather than merely slow.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Optional

from rig.cameras.base import Camera, DeviceInfo
from rig.cameras.pixels import BYTES_PER_PIXEL, buffer_to_image
from rig.errors import (
    CameraDisconnected,
    CameraTimeout,
    ConfigError,
    DeviceError,
    DeviceNotFound,
)
from sync.frames import Frame

if TYPE_CHECKING:  # annotations only: rig.config imports the sim backend to check [sim] options
    from rig.config import CameraConfig

SCHEME = "aravis"
N_BUFFERS = 16
SOCKET_BUFFER_MIN = 4 * 1024 * 1024
HARDWARE_TRIGGER_LINE = "Line0"

_Aravis = None


def _aravis():
    """Import Aravis lazily: machines without the GObject libraries can still run everything else."""
    global _Aravis
    if _Aravis is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as exc:
            raise DeviceError(
                f"Aravis 0.8 is not available ({exc}); install gir1.2-aravis-0.8 and `pip install 'pygobject>=3.48,<3.51'`"
            ) from None
        _Aravis = Aravis
    return _Aravis


def discover() -> list[DeviceInfo]:
    Aravis = _aravis()
    Aravis.update_device_list()
    devices = []
    for i in range(Aravis.get_n_devices()):
        address = Aravis.get_device_address(i) or ""
        device_id = Aravis.get_device_id(i) or ""
        devices.append(
            DeviceInfo(
                uri=f"aravis://{address or device_id}",
                backend=SCHEME,
                model=Aravis.get_device_model(i) or "",
                serial=Aravis.get_device_serial_nbr(i) or "",
                vendor=Aravis.get_device_vendor(i) or "",
                address=address,
                extra={"id": device_id, "protocol": Aravis.get_device_protocol(i) or ""},
            )
        )
    return devices


def open(uri: str, settings: CameraConfig) -> "AravisCamera":  # noqa: A001
    return AravisCamera(uri, settings)


class AravisCamera(Camera):
    def __init__(self, uri: str, settings: CameraConfig, n_buffers: int = N_BUFFERS):
        super().__init__(uri, settings)
        Aravis = _aravis()
        self._Aravis = Aravis
        self.device_name = uri.split("://", 1)[1].strip("/")
        if not self.device_name:
            raise ConfigError(f"{uri}: an aravis URI names the camera by address or id, e.g. aravis://192.168.1.20")
        try:
            self._cam = Aravis.Camera.new(self.device_name)
        except Exception as exc:  # GLib.Error: no such device
            raise DeviceNotFound(f"{uri}: no camera answers ({_glib_message(exc)}); `rig discover` lists the cameras found") from None
        self._dev = self._cam.get_device()
        self._stream = None
        self._n_buffers = n_buffers
        self._running = False
        self._closed = False
        self._lost = False
        self.is_gv = bool(self._cam.is_gv_device())
        self.FRAME_ID_MODULUS = 65536 if self.is_gv else None  # GigE Vision 1.x: 16-bit ids, 0 skipped
        self.model = self._cam.get_model_name() or ""
        self.serial = self._cam.get_device_serial_number() or ""
        self._configure()
        self._reported = {"exposure_us": self._read(self._exposure_feature()), "gain": self._read(self._gain_feature())}

    # --- configuration ---------------------------------------------------------------------------
    def _has(self, feature: str) -> bool:
        try:
            return bool(self._cam.is_feature_available(feature))
        except Exception:
            return False

    def _set(self, feature: str, value: Any) -> None:
        cam = self._cam
        try:
            if isinstance(value, bool):
                cam.set_boolean(feature, value)
            elif isinstance(value, str):
                cam.set_string(feature, value)
            elif isinstance(value, int):
                cam.set_integer(feature, value)
            else:
                cam.set_float(feature, float(value))
        except Exception as exc:
            raise DeviceError(f"{self.uri}: camera rejected {feature} = {value!r} ({_glib_message(exc)})") from None

    def _configure(self) -> None:
        s = self.settings
        cam = self._cam
        if self.is_gv:
            # The packet socket needs raw-socket rights and sees nothing on loopback; the standard
            # UDP socket path works everywhere.
            cam.gv_set_stream_options(self._Aravis.GvStreamOption.PACKET_SOCKET_DISABLED)
        formats = list(cam.dup_available_pixel_formats_as_strings() or [])
        if s.pixel_format not in formats:
            raise ConfigError(f"{self.name}.pixel_format: {s.pixel_format!r} not offered by {self.uri} (offers: {', '.join(formats)})")
        self._set("PixelFormat", s.pixel_format)
        try:
            cam.set_region(0, 0, s.width, s.height)
        except Exception as exc:
            raise DeviceError(f"{self.uri}: cannot set region {s.width}x{s.height} ({_glib_message(exc)})") from None
        _, _, w, h = cam.get_region()
        if (w, h) != (s.width, s.height):
            wb, hb = cam.get_width_bounds(), cam.get_height_bounds()
            raise ConfigError(
                f"{self.name}: {self.uri} cannot deliver {s.width}x{s.height} (got {w}x{h}; width {wb[0]}..{wb[1]}, height {hb[0]}..{hb[1]})"
            )
        if s.exposure_us is not None:
            if self._has("ExposureAuto"):
                self._set("ExposureAuto", "Off")
            self._set("ExposureTime" if self._has("ExposureTime") else "ExposureTimeAbs", float(s.exposure_us))
        if s.gain is not None:
            if self._has("GainAuto"):
                self._set("GainAuto", "Off")
            if self._has("Gain"):
                self._set("Gain", float(s.gain))
            else:
                self._set("GainRaw", int(round(s.gain)))
        if self._has("AcquisitionFrameRateEnable"):
            self._set("AcquisitionFrameRateEnable", True)
        for feature in ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"):
            if self._has(feature):
                self._set(feature, float(s.fps))
                break
        self._configure_trigger(s.trigger)
        cam.set_acquisition_mode(self._Aravis.AcquisitionMode.CONTINUOUS)

    def _configure_trigger(self, mode: str) -> None:
        if not self._has("TriggerMode"):
            if mode != "free":
                raise ConfigError(f"{self.name}.trigger: {self.uri} has no TriggerMode feature; use trigger = \"free\"")
            return
        if self._has("TriggerSelector"):
            self._set("TriggerSelector", "FrameStart")
        if mode == "free":
            self._set("TriggerMode", "Off")
            return
        source = "Software" if mode == "software" else HARDWARE_TRIGGER_LINE
        sources = list(self._cam.dup_available_enumerations_as_strings("TriggerSource") or [])
        if source not in sources:
            raise ConfigError(f"{self.name}.trigger: {self.uri} offers no TriggerSource {source!r} (offers: {', '.join(sources)})")
        self._set("TriggerSource", source)
        if mode == "hardware" and self._has("TriggerActivation"):
            self._set("TriggerActivation", "RisingEdge")
        self._set("TriggerMode", "On")

    # --- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        if self._closed:
            raise CameraDisconnected(f"{self.name} ({self.uri}): camera is closed")
        if self._running:
            return
        Aravis = self._Aravis
        try:
            stream = self._cam.create_stream(None, None)
        except Exception as exc:
            raise DeviceError(f"{self.uri}: cannot open a stream ({_glib_message(exc)})") from None
        payload = self._cam.get_payload()
        if self.is_gv:
            # Room for several frames in the kernel's receive buffer, so a busy host loses nothing
            # while the stream thread is descheduled (the kernel caps it at net.core.rmem_max).
            stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.FIXED)
            stream.set_property("socket-buffer-size", max(4 * payload, SOCKET_BUFFER_MIN))
        for _ in range(self._n_buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._stream = stream
        try:
            self._cam.start_acquisition()
        except Exception as exc:
            raise DeviceError(f"{self.uri}: cannot start acquisition ({_glib_message(exc)})") from None
        self._running = True
        self._realtime_offset_ns = time.time_ns() - time.monotonic_ns()
        if self.is_gv:
            self._prime_stream()

    def _prime_stream(self) -> None:
        """Take and discard one frame so the stream has sized its socket before real frames arrive.

        Aravis sizes the UDP receive buffer when the first frame begins; frames sent before its
        stream thread gets there land in the kernel's default buffer, which a busy host overflows
        (a loaded 2-core host lost 24 of the 60 packets of the second 320x240 frame at 100 fps).
        A software-triggered camera is primed with one trigger. A free-running one is primed with
        its first frame, then stopped and started again so that every frame the caller sees
        arrives into the sized buffer. A hardware-triggered camera is not primed (it sends nothing
        until the board fires): a first frame larger than the kernel's default buffer can be lost.
        """
        mode = self.settings.trigger
        if mode == "hardware":
            return
        try:
            if mode == "software":
                self._cam.software_trigger()
            buf = self._stream.timeout_pop_buffer(1_000_000)
        except Exception:
            return
        if buf is not None:
            self._stream.push_buffer(buf)
        if mode != "free":
            return
        try:
            self._cam.stop_acquisition()
            # drain the first run's frames, including a cut-off one the stream gives up on only
            # after its frame retention
            wait_us = int(self._stream.get_property("frame-retention")) + 50_000
            while (buf := self._stream.timeout_pop_buffer(wait_us)) is not None:
                self._stream.push_buffer(buf)
            self._cam.start_acquisition()
        except Exception as exc:
            raise DeviceError(f"{self.uri}: cannot restart acquisition ({_glib_message(exc)})") from None

    def stop(self) -> None:
        if not self._running:
            return
        self._running = False
        if not self._lost:  # a vanished camera cannot be stopped; frames already delivered stay valid
            try:
                self._cam.stop_acquisition()
            except Exception:
                self._lost = True
        self._stream = None  # unref: ends the stream thread and frees the buffer pool

    def close(self) -> None:
        self.stop()
        self._closed = True
        self._dev = None
        self._cam = None

    def reconnect(self) -> bool:
        """Open the device again by the same address or id (a camera powered back on or plugged in
        again), apply the same settings and restart acquisition. False while it does not answer."""
        if self._closed:
            return False
        if not self._lost and self._running:
            return True
        self.stop()
        try:
            cam = self._Aravis.Camera.new(self.device_name)
        except Exception:  # GLib.Error: not there (yet)
            return False
        self._cam, self._dev = cam, cam.get_device()
        self._lost = False
        self._last_frame_id = None  # a new acquisition: the device counts frames afresh
        try:
            self._configure()
            self.start()
        except (DeviceError, ConfigError):
            self._lost, self._running = True, False
            return False
        return True

    # --- frames ----------------------------------------------------------------------------------
    def software_trigger(self) -> None:
        if self._closed or self._lost:
            raise CameraDisconnected(f"{self.name} ({self.uri}): camera disconnected")
        if self.settings.trigger != "software":
            raise ConfigError(f"{self.name}: software trigger fired but the camera is in '{self.settings.trigger}' mode")
        try:
            self._cam.software_trigger()
        except Exception as exc:
            # A control-channel timeout already means the device stopped answering; anything else
            # (e.g. an access error) is checked with one more read.
            self._lost = "timeout" in _glib_message(exc).lower() or not self._answers()
            if self._lost:
                raise CameraDisconnected(f"{self.name} ({self.uri}): camera stopped answering ({_glib_message(exc)})") from None
            raise DeviceError(f"{self.name} ({self.uri}): software trigger failed ({_glib_message(exc)})") from None

    def _answers(self) -> bool:
        """Whether the device still answers a control read (bypasses nothing: a real register read)."""
        try:
            self._dev.get_integer_feature_value("Width")
            return True
        except Exception:
            return False

    def _read_frame(self, timeout: float) -> Frame:
        if self._stream is None:
            raise DeviceError(f"{self.name} ({self.uri}): get_frame before start()")
        if self._lost:
            raise CameraDisconnected(f"{self.name} ({self.uri}): camera disconnected")
        SUCCESS = self._Aravis.BufferStatus.SUCCESS
        deadline = time.monotonic() + timeout
        while True:
            remaining_us = max(1, int((deadline - time.monotonic()) * 1e6))
            buf = self._stream.timeout_pop_buffer(remaining_us)
            if buf is None:
                self.stats.timeouts += 1
                if not self._answers():
                    self._lost = True
                    raise CameraDisconnected(f"{self.name} ({self.uri}): camera stopped answering (unplugged or powered off?)")
                raise CameraTimeout(f"{self.name} ({self.uri}): no frame within {timeout:.3f} s")
            if buf.get_status() != SUCCESS:
                self.stats.incomplete += 1
                self._stream.push_buffer(buf)
                if time.monotonic() >= deadline:
                    raise CameraTimeout(f"{self.name} ({self.uri}): no complete frame within {timeout:.3f} s")
                continue
            try:
                return self._decode(buf)
            finally:
                self._stream.push_buffer(buf)

    # --- exposure and gain while acquiring (GenICam features, read back from the device) ----------------
    def _exposure_feature(self) -> Optional[str]:
        return next((f for f in ("ExposureTime", "ExposureTimeAbs") if self._has(f)), None)

    def _gain_feature(self) -> Optional[str]:
        return next((f for f in ("Gain", "GainRaw") if self._has(f)), None)

    def _read(self, feature: Optional[str]) -> Optional[float]:
        if feature is None:
            return None
        try:
            return float(self._cam.get_integer(feature) if feature == "GainRaw" else self._cam.get_float(feature))
        except Exception:
            return None

    def _bounds(self, feature: Optional[str]) -> Optional[list[float]]:
        if feature is None:
            return None
        try:
            lo, hi = (self._cam.get_integer_bounds(feature) if feature == "GainRaw" else self._cam.get_float_bounds(feature))
            return [float(lo), float(hi)]
        except Exception:
            return None

    def controls(self) -> dict:
        exposure, gain = self._exposure_feature(), self._gain_feature()
        ranges = {k: b for k, b in (("exposure_us", self._bounds(exposure)), ("gain", self._bounds(gain))) if b is not None}
        self._reported = {"exposure_us": self._read(exposure), "gain": self._read(gain)}
        return {**self._reported, "ranges": ranges, "live": True}

    def set_controls(self, exposure_us=None, gain=None) -> dict:
        from rig.cameras.base import check_control

        exposure, gain_feature = self._exposure_feature(), self._gain_feature()
        wanted = []
        for key, value, feature in (("exposure_us", exposure_us, exposure), ("gain", gain, gain_feature)):
            if value is None:
                continue
            if feature is None:
                raise DeviceError(f"{self.name}: {self.uri} has no {key.split('_')[0]} feature")
            bounds = self._bounds(feature) or [0.0, float("inf")]
            wanted.append((feature, check_control(self.name, key, value, tuple(bounds))))
        for feature, value in wanted:  # all checked first: a bad value changes nothing
            auto = "ExposureAuto" if feature.startswith("Exposure") else "GainAuto"
            if self._has(auto):
                self._set(auto, "Off")
            self._set(feature, int(round(value)) if feature == "GainRaw" else float(value))
        return self.controls()

    def _decode(self, buf) -> Frame:
        s = self.settings
        width, height = buf.get_image_width(), buf.get_image_height()
        data = buf.get_image_data()
        if len(data) < width * height * BYTES_PER_PIXEL[s.pixel_format]:
            raise DeviceError(f"{self.name}: buffer of {len(data)} bytes is short for {width}x{height} {s.pixel_format}")
        image = buffer_to_image(data, width, height, s.pixel_format, copy=False)
        return Frame(
            image=image,
            camera=self.name,
            frame_id=int(buf.get_frame_id()),
            device_ts_ns=int(buf.get_timestamp()),
            # the stream thread stamps arrival on the realtime clock; express it on the monotonic one
            host_ts_ns=int(buf.get_system_timestamp()) - self._realtime_offset_ns,
            pixel_format=s.pixel_format,
            # what the device reported when last read (opening, or a control change), not the config's wish
            exposure_us=(getattr(self, "_reported", None) or {}).get("exposure_us", self.settings.exposure_us),
        )

    def stream_statistics(self) -> dict[str, int]:
        """Aravis's own stream counters (completed buffers, failures, missing packets, ...)."""
        if self._stream is None:
            return {}
        st = self._stream
        return {st.get_info_name(i): int(st.get_info_uint64(i)) for i in range(st.get_n_infos())}


def _glib_message(exc: BaseException) -> str:
    return getattr(exc, "message", None) or str(exc) or type(exc).__name__
