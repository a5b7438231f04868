"""Frame sources: a synthetic camera pattern, an OpenCV capture device, and a simulated ultrasound probe.

The ultrasound image is rendered by a pure function of the contact force and a random generator: out of
contact the probe sees only its own ring-down; in contact, tissue layers appear under a speckle pattern,
brighter with better coupling (more force) and compressed by the pressure, and the speckle changes every
frame as real speckle does when the probe moves.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from iorthand_edge.perception.camera import Frame, device_frame_time_ns, open_device_capture
from iorthand_edge.video.config import StreamConfig

Image = NDArray[np.uint8]


class VideoError(RuntimeError):
    """A frame source that cannot be used; the message says why."""


class FrameSource(ABC):
    description = "a frame source"  # what the operator reads when it fails: "no frame from <description> …"
    # True: grab() itself waits for the source's next frame, and the stream runs at the source's rate, not its own.
    paced = False

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def grab(self) -> Image | None:
        """The next frame (BGR or grey), or None if none is available now."""

    def close(self) -> None:  # noqa: B027 (optional)
        pass

    def frame_time_ns(self, returned_ns: int) -> int:
        """The capture time (wall clock, ns) of the frame grab() returned at ``returned_ns``: that, unless the
        source knows better (a device's driver stamp: its frames may have waited in buffers)."""
        return returned_ns


class PatternSource(FrameSource):
    """Colour bars drifting over a fixed noise texture, with a frame counter and a camera's sensor noise (a few
    grey levels, different in every frame): JPEG and H.264 sizes like a real scene (an encoder that could
    predict every frame from the last would make any link look wide enough)."""

    description = "the test pattern"

    def __init__(self, width: int, height: int, seed: int = 1) -> None:
        self.size = (width, height)
        rng = np.random.default_rng(seed)
        noise = rng.integers(0, 60, (height, width, 1), dtype=np.uint8)
        bars = np.zeros((height, width, 3), dtype=np.uint8)
        colours = [(255, 255, 255), (0, 255, 255), (255, 255, 0), (0, 255, 0), (255, 0, 255), (0, 0, 255), (255, 0, 0)]
        for i, c in enumerate(colours):
            bars[:, i * width // 7 : (i + 1) * width // 7] = c
        self._base = cv2.add(bars // 2, np.repeat(noise, 3, axis=2))
        # Sensor noise: a few fields drawn once and taken in turn (drawing one per frame costs more than the frame).
        self._grain = [rng.integers(0, 5, (height, width, 3), dtype=np.uint8) for _ in range(7)]
        self._n = 0

    def open(self) -> None:
        pass

    def grab(self) -> Image:
        self._n += 1
        frame = cv2.add(np.roll(self._base, (self._n * 4) % self.size[0], axis=1), self._grain[self._n % 7])
        cv2.putText(frame, f"{self._n}", (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (255, 255, 255), 2)
        return frame


class OpenCVSource(FrameSource):
    def __init__(self, config: StreamConfig) -> None:
        self.config = config
        self.description = f"video device {config.device!r}"
        self._cap: cv2.VideoCapture | None = None
        self._frame_ns: int | None = None  # the driver's capture time of the last frame grab() returned

    def open(self) -> None:
        device: int | str = int(self.config.device) if self.config.device.isdigit() else self.config.device
        cap = open_device_capture(device)
        if not cap.isOpened():
            raise VideoError(f"cannot open video device {self.config.device!r}: is it plugged in and free?")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.height)
        cap.set(cv2.CAP_PROP_FPS, self.config.fps)
        # Cameras often ignore the requested mode. H.264 takes only the configured size: say so now, naming both
        # sizes (JPEG frames carry their own size). A backend that reports 0 is checked at the first frame.
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if self.config.codec == "h264" and w > 0 and h > 0 and (w, h) != (self.config.width, self.config.height):
            cap.release()
            raise VideoError(f"{self.description} delivers {w}×{h} frames, the H.264 stream is configured for "
                             f"{self.config.width}×{self.config.height}: set the stream's width/height to the "
                             "device's size")
        self._cap = cap

    def grab(self) -> Image | None:
        if self._cap is None:
            raise VideoError("video device used before open()")
        self._frame_ns = None
        if not self._cap.grab():
            return None
        self._frame_ns = device_frame_time_ns(self._cap.get(cv2.CAP_PROP_POS_MSEC), time.time_ns(), time.monotonic_ns())
        ok, frame = self._cap.retrieve()
        return frame if ok else None

    def frame_time_ns(self, returned_ns: int) -> int:
        return returned_ns if self._frame_ns is None else self._frame_ns

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


@lru_cache(maxsize=4)
def _tissue(width: int, height: int) -> NDArray[np.float32]:
    """Echogenicity of a phantom (rows = depth): skin line, fat, striated muscle, a round anechoic vessel."""
    y = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    x = np.linspace(0.0, 1.0, width, dtype=np.float32)[None, :]
    echo = np.full((height, width), 0.35, dtype=np.float32)
    echo = np.where(y < 0.04, 1.0, echo)  # skin: a bright line
    echo = np.where((y >= 0.04) & (y < 0.20), 0.18, echo)  # fat: dark
    striae = 0.45 + 0.25 * np.sin(2 * np.pi * (y * 28 + 0.15 * np.sin(2 * np.pi * x * 2)))
    echo = np.where((y >= 0.20) & (y < 0.75), striae, echo)  # muscle: striated
    echo = np.where(np.abs(y - 0.75) < 0.01, 1.0, echo)  # fascia / bone surface: bright
    vessel = (x - 0.55) ** 2 * (width / height) ** 2 + (y - 0.45) ** 2 < 0.09**2
    echo = np.where(vessel, 0.03, echo)  # vessel: anechoic
    return echo.astype(np.float32)


_SPECKLE_TEXTURES = 4  # speckle fields drawn once per image size; each frame shows one at a random offset
_SPECKLE_MARGIN = 48  # px of the half-resolution field beyond the frame: the offsets a frame can take per axis


@lru_cache(maxsize=4)
def _probe(width: int, height: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """What does not depend on the force, per row: the probe's ring-down (its own reverberation) plus the floor,
    and the attenuation with depth."""
    y = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    ringdown = 0.5 * np.exp(-y * 40.0) * (0.6 + 0.4 * np.cos(y * 300.0)) + 0.02
    base = np.ascontiguousarray(np.broadcast_to(ringdown, (height, width)), dtype=np.float32)
    return base, np.exp(-y * 1.6).astype(np.float32)


@lru_cache(maxsize=16)
def _compressed_tissue(width: int, height: int, rows: bytes) -> NDArray[np.float32]:
    """The tissue map sampled at ``rows`` (the depth each image row shows under pressure), attenuated. A force
    changes ``rows`` only every ~0.2 N, so a probe held in contact reuses one of a few of these."""
    index = np.frombuffer(rows, dtype=np.int64)
    return np.ascontiguousarray(_tissue(width, height)[index] * _probe(width, height)[1])


@lru_cache(maxsize=4)
def _speckle_bank(width: int, height: int) -> NDArray[np.float32]:
    """Rayleigh speckle fields at half resolution, drawn once (a fixed seed: the image stays a pure function
    of the force and the caller's generator, which picks the field and its offset)."""
    shape = (_SPECKLE_TEXTURES, height // 2 + _SPECKLE_MARGIN, width // 2 + _SPECKLE_MARGIN)
    return np.random.default_rng(0).rayleigh(0.8, shape).astype(np.float32)


def render_ultrasound(width: int, height: int, force: float, rng: np.random.Generator) -> Image:
    """One B-mode frame (grey) for a contact force in N. Pure given ``rng``.

    Everything that does not change from frame to frame is computed once and cached (the probe's ring-down,
    the attenuation, the compressed tissue map, the speckle fields): a frame costs a few image-wide
    operations instead of drawing and combining new random fields (4.8 → ~0.5 ms at 480×360 in contact)."""
    base, _ = _probe(width, height)
    coupling = 1.0 - math.exp(-max(force, 0.0) / 1.5)  # gel contact improves with pressure
    image = base
    if coupling > 0.01:
        # Pressure compresses the tissue toward the probe: sample the tissue map deeper for each row.
        compression = 1.0 + min(force, 20.0) * 0.015
        rows = np.clip((np.arange(height) * compression).astype(np.int64), 0, height - 1)
        image = cv2.scaleAdd(_compressed_tissue(width, height, rows.tobytes()), coupling, base)
    # Speckle changes every frame, as real speckle does when the probe moves: a random field at a random offset.
    bank = _speckle_bank(width, height)
    i = int(rng.integers(_SPECKLE_TEXTURES))
    dy, dx = (int(v) for v in rng.integers(0, _SPECKLE_MARGIN, 2))
    field = bank[i, dy : dy + height // 2, dx : dx + width // 2]
    speckle = cv2.resize(field, (width, height), interpolation=cv2.INTER_LINEAR)
    return cv2.multiply(image, speckle, scale=180.0, dtype=cv2.CV_8U)  # saturates to 0..255


class UltrasoundSimSource(FrameSource):
    description = "the simulated ultrasound probe"

    def __init__(self, config: StreamConfig, contact_force: Callable[[], float], seed: int | None = None) -> None:
        self.config = config
        self.contact_force = contact_force
        self._rng = np.random.default_rng(seed)

    def open(self) -> None:
        pass

    def grab(self) -> Image:
        return render_ultrasound(self.config.width, self.config.height, self.contact_force(), self._rng)


class SharedFrameSource(FrameSource):
    """Each image another component captured (the perception camera), as it arrives: one camera device feeds
    both the marker detection and the video stream. grab() waits up to :data:`WAIT` s for the next image and
    returns None if none came. Paced by the camera: polling it at the stream's own rate sent each image up to a
    period late, and at the camera's rate, with the two clocks drifting, would skip some and find none at others.
    Each video frame carries the perception frame's capture time (its markers carry the same), not the time this
    thread received it."""

    description = "the perception camera"
    paced = True
    WAIT = 0.2  # s: how soon a stop (or a stalled camera) is noticed

    def __init__(self, next_image: Callable[[Frame | None, float], Frame | None]) -> None:
        self._next_image = next_image
        self._last: Frame | None = None

    def open(self) -> None:
        pass

    def grab(self) -> Image | None:
        frame = self._next_image(self._last, self.WAIT)
        if frame is None:
            return None
        self._last = frame
        return frame.image

    def frame_time_ns(self, returned_ns: int) -> int:
        return returned_ns if self._last is None else self._last.t_ns


def make_source(
    config: StreamConfig, contact_force: Callable[[], float],
    shared_frame: Callable[[Frame | None, float], Frame | None] | None = None,
) -> FrameSource:
    if config.source == "perception":
        if shared_frame is None:
            raise VideoError("video source 'perception' needs the perception section (its camera feeds the video)")
        return SharedFrameSource(shared_frame)
    if config.source == "pattern":
        return PatternSource(config.width, config.height)
    if config.source == "opencv":
        return OpenCVSource(config)
    if config.source == "ultrasound_sim":
        return UltrasoundSimSource(config, contact_force)
    raise ValueError(f"unknown video source {config.source!r}")
