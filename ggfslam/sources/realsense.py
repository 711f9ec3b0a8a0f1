"""Intel RealSense input through ``pyrealsense2`` (``pip install 'ggfslam[realsense]'``): a camera, or a recording
made by the RealSense Viewer or ``rs-record`` (``.bag``; librealsense 2.57+ writes ROS 2 ``.db3``), played back on
its own clock through the same pipeline.

Colour and depth are streamed at the same resolution, depth aligned to colour by librealsense (``rs.align``); the
intrinsics are the colour stream's and the depth scale is the depth sensor's, both read from the device (or the
recording). Frames the run takes are recorded in the run folder (``input/``, TUM layout, depth in millimetres), so
the run can be evaluated, rendered, viewed and run again offline.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ggfslam.data.types import Camera, Frame
from ggfslam.sources.base import RECORDING_DIR, LiveSequence, LiveSource, SourceError, log

RECORDING_SUFFIXES = (".bag", ".db3")
NO_FRAMES_SECONDS = 5.0  # a camera that sends nothing for this long ends the input with an error


def import_pyrealsense2():
    """The ``pyrealsense2`` module, or a SourceError saying how to install it."""
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise SourceError(f"--source realsense needs the pyrealsense2 package ({e}); install it with "
                          "pip install 'ggfslam[realsense]'") from None
    return rs


class RealSenseSource(LiveSource):
    """A RealSense camera (``serial``: which one, when several are connected) or a recording (``recording``)."""

    def __init__(self, serial: str | None = None, recording: str | Path | None = None, width: int = 640,
                 height: int = 480, fps: int = 30, capacity: int = 2):
        super().__init__(capacity)
        if recording is not None:
            recording = Path(recording)
            if not recording.is_file():
                raise SourceError(f"{recording}: RealSense recording not found")
            if recording.suffix not in RECORDING_SUFFIXES:
                raise SourceError(f"{recording}: a RealSense recording ends in {' or '.join(RECORDING_SUFFIXES)}")
        self.serial, self.recording, self.width, self.height, self.fps = serial, recording, width, height, fps
        self._pipe = None
        self._streaming = False
        self._playback = None
        self.device_name = ""

    def describe(self) -> str:
        """One line naming the source, for metrics.json and logs."""
        if self.recording is not None:
            return f"RealSense recording {self.recording}, queue of {self.queue.capacity}"
        name = self.device_name or "RealSense"
        return f"{name} {self.width}x{self.height} at {self.fps} Hz, queue of {self.queue.capacity}"

    def open(self, config, out_dir: Path):
        """Find the camera (or open the recording) and read its intrinsics and depth scale; the frames the run takes
        will be recorded into ``out_dir/input``."""
        rs = import_pyrealsense2()
        cfg = rs.config()
        if self.recording is not None:
            cfg.enable_device_from_file(str(self.recording), repeat_playback=False)
        else:
            self._choose_device(rs, cfg)
            cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
            cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, self.fps)
        pipe = rs.pipeline()
        try:  # the device and its streams, without streaming yet (a recording would play to nobody)
            profile = cfg.resolve(rs.pipeline_wrapper(pipe))
            device = profile.get_device()
            self.device_name = device.get_info(rs.camera_info.name) if device.supports(rs.camera_info.name) else ""
            self.depth_scale = float(device.first_depth_sensor().get_depth_scale())  # metres per depth unit
            camera = _camera(profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics(), rs)
        except RuntimeError as e:
            what = self.recording or "the camera"
            raise SourceError(f"{what}: librealsense finds no colour and depth streams to use ({e})") from None
        self._pipe, self._cfg = pipe, cfg
        self._align = rs.align(rs.stream.color)
        self._rs = rs
        folder = Path(out_dir) / RECORDING_DIR
        self.sequence = LiveSequence(camera, self.describe(), folder, depth_scale=1000.0)
        log.info("%s: %dx%d, fx %.1f fy %.1f, depth scale %.6g m", self.describe(), camera.width, camera.height,
                 camera.fx, camera.fy, self.depth_scale)
        from ggfslam.config import DatasetConfig

        d = config.dataset  # the recording replaces the configured sequence; its bad-frame policy stays
        dataset = DatasetConfig(kind="tum", path=str(folder), on_bad_frame=d.on_bad_frame,
                                max_bad_frames=d.max_bad_frames)
        return self.sequence, config.model_copy(update={"dataset": dataset})

    def start(self) -> RealSenseSource:
        """Start streaming (a recording plays from its start, on its own clock)."""
        try:
            profile = self._pipe.start(self._cfg)
        except RuntimeError as e:
            raise SourceError(f"{self.recording or 'the camera'}: librealsense cannot start streaming ({e})") from None
        self._streaming = True
        if self.recording is not None:
            self._playback = profile.get_device().as_playback()
            self._playback.set_real_time(True)  # as the camera delivered it
        return super().start()

    def _choose_device(self, rs, cfg) -> None:
        devices = rs.context().query_devices()
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        if not serials:
            raise SourceError("no RealSense camera found: is it connected (USB 3), and may this user open it "
                              "(librealsense's udev rules)?")
        if self.serial is not None:
            if self.serial not in serials:
                raise SourceError(f"no RealSense camera with serial {self.serial}; connected: {', '.join(serials)}")
            cfg.enable_device(self.serial)
        elif len(serials) > 1:
            log.info("%d RealSense cameras connected (%s): using the first; choose with realsense:SERIAL",
                     len(serials), ", ".join(serials))

    def _drive(self) -> None:
        rs = self._rs
        quiet = 0.0
        last_ts = -np.inf
        while not self._stop.is_set():
            ok, frames = self._pipe.try_wait_for_frames(200)
            if not ok:
                if self._playback is not None and self._playback.current_status() == rs.playback_status.stopped:
                    return  # the recording has ended
                quiet += 0.2
                if quiet >= NO_FRAMES_SECONDS and self._playback is None:
                    raise SourceError(f"no frames from the camera for {NO_FRAMES_SECONDS:g} s")
                continue
            quiet = 0.0
            arrived = time.perf_counter()
            aligned = self._align.process(frames)
            depth_f, colour_f = aligned.get_depth_frame(), aligned.get_color_frame()
            if not depth_f or not colour_f:
                continue
            rgb = _rgb(colour_f, rs)  # [H, W, 3]
            depth = np.asanyarray(depth_f.get_data()).astype(np.float32) * np.float32(self.depth_scale)  # [H, W] m
            ts = max(frames.get_timestamp() / 1000.0, last_ts + 1e-6)  # ms; strictly increasing file names
            last_ts = ts
            i = self.sequence.add_stamp(ts)
            self._deliver(i, arrived, arrived, Frame(i, ts, rgb, depth))

    def _release(self) -> None:
        if self._streaming:
            try:
                self._pipe.stop()
            except RuntimeError:  # already stopped (the recording ended)
                pass
            self._streaming = False


def _rgb(frame, rs) -> np.ndarray:
    """Colour frame as float32 RGB [H, W, 3] in [0, 1]."""
    fmt = frame.get_profile().format()
    data = np.asanyarray(frame.get_data())
    if fmt == rs.format.rgb8:
        img = data
    elif fmt == rs.format.bgr8:
        img = data[..., ::-1]
    else:
        raise SourceError(f"colour stream format {fmt} is not supported: stream or record rgb8 or bgr8")
    return img.astype(np.float32) / np.float32(255.0)


def _camera(intr, rs) -> Camera:
    """The colour stream's intrinsics (depth is aligned to it), with its distortion when OpenCV's model fits (the run
    reads the frames undistorted, see ``LiveSequence``)."""
    coeffs = tuple(float(c) for c in intr.coeffs)
    distortion: tuple[float, ...] = ()
    if any(abs(c) > 1e-12 for c in coeffs):
        if intr.model == rs.distortion.brown_conrady:  # k1 k2 p1 p2 k3, OpenCV's order
            distortion = coeffs
        else:
            log.warning("colour stream distortion model %s is not OpenCV's: treated as undistorted", intr.model)
    return Camera(float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy), int(intr.width), int(intr.height),
                  1000.0, distortion)
