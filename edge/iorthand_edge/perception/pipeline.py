"""The perception pipeline: frame → ArUco → corners from the edges → IPPE pose → chain to the base frame → filter → ``Markers``.

:meth:`PerceptionPipeline.start` runs capture and processing in a named worker thread that never blocks the
caller; :meth:`PerceptionPipeline.process` does one frame synchronously (tests, benchmarks). Configuration
problems (missing or wrong-size calibration, a bad file) raise :class:`PerceptionError` from the constructor
with the reason. A camera that cannot be opened or stops delivering does not end the worker: the reason goes
to :attr:`PerceptionPipeline.failure`, to the log, and out as a ``Markers`` message with ``failure`` set, and
the camera is reopened every ``retry_interval`` s until it delivers again (an unplugged USB camera that is
plugged back in). Only a source that is finished (the end of a video file) ends the worker. The rest of the
agent keeps running throughout.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from iorthand.geometry import compose, flatten, pose_to_matrix
from iorthand.process import name_thread
from iorthand.protocol import MarkerPose, Markers, Sequencer

from .calibration import CalibrationError, load_handeye, load_intrinsics
from .camera import CameraError, CameraFinished, CameraSource, Frame, make_camera
from .chain import CameraChain
from .config import PerceptionConfig, SyntheticCameraConfig
from .detector import detect_markers, estimate_marker_pose, make_aruco_detector, marker_bits, refine_detections
from .filter import MarkerFilters
from .synthetic import camera_matrix

log = logging.getLogger(__name__)

_FPS_WINDOW = 30  # frames over which the published frame rate is measured
_WARN_EVERY_S = 5.0


class PerceptionError(RuntimeError):
    """The pipeline cannot run; the message says why."""


@dataclass
class StageTimes:
    """Milliseconds spent in each stage of the last processed frame."""

    convert: float = 0.0
    detect: float = 0.0
    refine: float = 0.0  # corners from the markers' edges
    pose: float = 0.0
    chain: float = 0.0
    filter: float = 0.0
    total: float = 0.0


@dataclass
class PipelineStats:
    frames: int = 0
    frames_without_robot_pose: int = 0
    publish_errors: int = 0
    camera_failures: int = 0  # failed attempts to open or read the camera
    stages: StageTimes = field(default_factory=StageTimes)


class PerceptionPipeline:
    def __init__(
        self,
        config: PerceptionConfig,
        robot_pose_at: Callable[[int], np.ndarray | None],
        servo_angles_at: Callable[[int], tuple[float, float] | None],
        publish: Callable[[Markers], None],
        camera: CameraSource | None = None,
    ) -> None:
        self.config = config
        self.robot_pose_at = robot_pose_at
        self.servo_angles_at = servo_angles_at
        self.publish = publish
        self.image_size = config.camera.image_size()
        self.camera_matrix, self.dist_coeffs, self.calibrated_size = self._intrinsics(config)
        self.chain = self._chain(config)
        self.detector = make_aruco_detector(config.detector)
        self._dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.detector.dictionary))
        self._bits: dict[int, np.ndarray] = {}  # each seen marker's printed pattern, for the edge refinement
        self.filters = MarkerFilters(config.filter)
        self.stats = PipelineStats()
        # The newest camera frame (shared with the video stream through next_image, so one camera serves both).
        self._image: Frame | None = None
        self._image_arrived = threading.Condition()
        self.failure: str | None = None
        self._camera = camera
        self._sequencer = Sequencer()
        self._recent_frame_times: deque[int] = deque(maxlen=_FPS_WINDOW)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._active_camera: CameraSource | None = None  # the worker's, for stop() to interrupt
        self._last_warning = 0.0

    # -- set-up ------------------------------------------------------------------------------------------

    def _intrinsics(self, config: PerceptionConfig) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        if config.intrinsics_file is not None:
            try:
                intrinsics = load_intrinsics(config.intrinsics_file, self.image_size)
            except CalibrationError as exc:
                raise PerceptionError(str(exc)) from None
            return intrinsics.matrix(), intrinsics.distortion(), intrinsics.image_size
        if isinstance(config.camera, SyntheticCameraConfig):
            c = config.camera
            return camera_matrix(c), np.zeros(5), (c.width, c.height)
        raise PerceptionError(
            f"the {type(config.camera).__name__} needs intrinsics_file (make one with `iorthand calibrate intrinsics`)"
        )

    def _chain(self, config: PerceptionConfig) -> CameraChain:
        if config.handeye_file is None:
            return CameraChain(config.geometry)
        try:
            handeye = load_handeye(config.handeye_file, self.calibrated_size)
        except CalibrationError as exc:
            raise PerceptionError(str(exc)) from None
        # Re-derive T_tilt_camera with this config's mount so a changed mount geometry cannot go unnoticed
        # behind a stale value stored in the file.
        chain = CameraChain(config.geometry)
        chain.t_tilt_camera = chain.tilt_camera_from_tcp_camera(
            pose_to_matrix(handeye.tcp_camera), handeye.pan, handeye.tilt
        )
        return chain

    # -- one frame ---------------------------------------------------------------------------------------

    def process(self, frame: Frame) -> Markers:
        """Detect, estimate, chain and filter the markers of one frame; the message is stamped with its time."""
        if frame.size != self.calibrated_size:
            raise PerceptionError(
                f"frame is {frame.size[0]}×{frame.size[1]} but the intrinsics are for "
                f"{self.calibrated_size[0]}×{self.calibrated_size[1]}; recalibrate or change the camera size"
            )
        times = StageTimes()
        start = time.perf_counter()
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        mark = time.perf_counter()
        times.convert = (mark - start) * 1e3
        detections = detect_markers(self.detector, gray)
        now = time.perf_counter()
        times.detect, mark = (now - mark) * 1e3, now

        markers: list[MarkerPose] = []
        t_base_tcp = self.robot_pose_at(frame.t_ns) if detections else None
        angles = self.servo_angles_at(frame.t_ns) if t_base_tcp is not None else None
        if detections and (t_base_tcp is None or angles is None):
            self.stats.frames_without_robot_pose += 1
            self._warn(
                "no robot pose at the frame's capture time: markers seen but not published (is the robot state flowing?)"
                if t_base_tcp is None else
                "no servo angles at the frame's capture time (none received, or the newest is older than a few "
                "servo heartbeats): markers seen but not published (is the servo state flowing?)"
            )
        elif detections and t_base_tcp is not None and angles is not None:
            pan, tilt = angles
            t_base_camera = self.chain.base_camera(t_base_tcp, pan, tilt)
            r_camera_base = t_base_camera[:3, :3].T
            detector = self.config.detector
            if detector.edge_refinement:
                mark = time.perf_counter()
                detections = refine_detections(
                    gray, detections, self.camera_matrix, self.dist_coeffs, self._marker_bits, detector
                )
                now = time.perf_counter()
                times.refine, mark = (now - mark) * 1e3, now
            for detection in detections:
                estimate = estimate_marker_pose(
                    detection.corners,
                    self.config.markers.size_of(detection.id),
                    self.camera_matrix,
                    self.dist_coeffs,
                    self._expected_normal(detection.id, r_camera_base),
                    corner_sigma=detector.corner_sigma if detection.corner_sigma is None else detection.corner_sigma,
                    normal_sigma=self.config.markers.normal_sigma,
                )
                now = time.perf_counter()
                times.pose, mark = times.pose + (now - mark) * 1e3, now
                if estimate is None:
                    continue
                raw = compose(t_base_camera, estimate.t_camera_marker)
                now = time.perf_counter()
                times.chain, mark = times.chain + (now - mark) * 1e3, now
                filtered = self.filters.update(detection.id, frame.t_ns, raw)
                now = time.perf_counter()
                times.filter, mark = times.filter + (now - mark) * 1e3, now
                markers.append(
                    MarkerPose(
                        id=detection.id,
                        pose=flatten(filtered),
                        raw=flatten(raw),
                        reprojection_error=estimate.reprojection_error,
                        pixel_size=estimate.pixel_size,
                    )
                )
        times.total = (time.perf_counter() - start) * 1e3
        self.stats.frames += 1
        self.stats.stages = times
        self._recent_frame_times.append(frame.t_ns)
        return Markers(
            seq=self._sequencer.next(),
            t=frame.t_ns,
            markers=markers,
            frames=self.stats.frames,
            fps=self._fps(),
            processing_ms=times.total,
        )

    def _marker_bits(self, marker_id: int) -> np.ndarray:
        bits = self._bits.get(marker_id)
        if bits is None:
            bits = self._bits[marker_id] = marker_bits(self._dictionary, marker_id)
        return bits

    def _expected_normal(self, marker_id: int, r_camera_base: np.ndarray) -> np.ndarray | None:
        normal = self.config.markers.expected_normals.get(marker_id, self.config.markers.expected_normal)
        if normal is None:
            return None
        n = r_camera_base @ np.asarray(normal, dtype=float)
        return n / np.linalg.norm(n)

    def next_image(self, after: Frame | None, timeout: float) -> Frame | None:
        """The camera's newest frame once it is another than ``after``, waiting up to ``timeout`` s for it (None
        if none came). The video stream takes each image as it arrives, before the markers are looked for, and
        stamps it with the frame's capture time (the driver's, when the camera has it), not its own receipt."""
        with self._image_arrived:
            self._image_arrived.wait_for(lambda: self._image is not None and self._image is not after, timeout)
            image = self._image
        return image if image is not after else None

    def _fps(self) -> float:
        times = self._recent_frame_times
        if len(times) < 2 or times[-1] <= times[0]:
            return 0.0
        return (len(times) - 1) / ((times[-1] - times[0]) / 1e9)

    def _warn(self, message: str) -> None:
        now = time.monotonic()
        if now - self._last_warning >= _WARN_EVERY_S:
            self._last_warning = now
            log.warning("perception: %s", message)

    # -- worker ------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the camera and process frames in the ``perception`` thread; returns at once."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self.failure = None
        self._thread = threading.Thread(target=self._run, name="perception", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        camera = self._active_camera
        if camera is not None:
            camera.interrupt()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("perception: worker still blocked in the camera after %.1f s; left as a daemon", timeout)
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        name_thread("perception")
        camera = self._camera or make_camera(self.config, self.robot_pose_at, self.servo_angles_at)
        self._active_camera = camera
        while not self._stop.is_set():
            try:
                self._stream(camera)
            except CameraFinished as exc:
                self._failed(str(exc), final=True)
                return
            except (CameraError, PerceptionError) as exc:
                if self._stop.is_set():
                    return  # interrupted by stop(): not a failure
                self._failed(str(exc))
            except Exception as exc:  # a bug: as visible as a camera failure, and retried the same way
                reason = f"internal error: {exc!r}"
                if reason != self.failure:  # the traceback once, not at every retry
                    log.exception("perception: internal error")
                self._failed(reason)
            finally:
                camera.close()
            self._stop.wait(self.config.retry_interval)

    def _stream(self, camera: CameraSource) -> None:
        """Open the camera and process its frames until stopped; camera and pipeline errors propagate."""
        camera.open()
        log.info("perception: %s open", camera.description)
        while not self._stop.is_set():
            frame = camera.read()
            with self._image_arrived:
                self._image = frame
                self._image_arrived.notify_all()
            self._publish(self.process(frame))
            if self.failure is not None:  # cleared only once frames flow again, so a flapping camera stays failed
                log.info("perception: %s delivers frames again", camera.description)
                self.failure = None

    def _failed(self, reason: str, final: bool = False) -> None:
        self.stats.camera_failures += 1
        if reason != self.failure:
            log.error("perception stopped: %s%s", reason, "" if final else f" (retrying every {self.config.retry_interval:g} s)")
        self.failure = reason
        self._publish(Markers(seq=self._sequencer.next(), t=time.time_ns(), frames=self.stats.frames, failure=reason))

    def _publish(self, message: Markers) -> None:
        try:
            self.publish(message)
        except Exception:  # a failing publisher must not end perception; count and log it
            self.stats.publish_errors += 1
            log.exception("perception: publishing markers failed")
