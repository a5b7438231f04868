"""A synthetic camera: renders the scene's ArUco markers (or a ChArUco board) as a pinhole camera sees them.

Planar textures are warped with their exact homography, rendered ``supersample`` times larger and
area-averaged down, so edges are anti-aliased the way a real sensor integrates light; then optional blur and
Gaussian noise. Intrinsics are known and there is no lens distortion.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from iorthand.geometry import Matrix, compose, invert, make_transform, pose_to_matrix, rotvec_to_matrix

from .camera import CameraError, CameraSource, Frame, _sleep_until
from .chain import CameraChain
from .config import PerceptionConfig, SceneConfig, SyntheticCameraConfig

_NEAR = 0.01  # m: anything closer to the camera than this is not rendered
_QUIET_ZONE_CELLS = 1  # white margin around a printed marker, in marker cells


def camera_matrix(config: SyntheticCameraConfig) -> NDArray[np.float64]:
    return np.array([[config.fx, 0.0, config.cx], [0.0, config.fy, config.cy], [0.0, 0.0, 1.0]])


@dataclass
class PlanarTexture:
    """An image lying on a plane. ``corners`` are the plane-frame 3-D points (m) of the texture's outer
    corners in the order top-left, top-right, bottom-right, bottom-left of the image."""

    image: NDArray[np.uint8]
    corners: NDArray[np.float64]
    front: float = 1.0  # +1: the printed side faces the plane frame's +z (a marker); -1: its -z (a board)


def marker_texture(dictionary: cv2.aruco.Dictionary, marker_id: int, size: float, cell_px: int = 24) -> PlanarTexture:
    """A marker of side ``size`` (the black square) with a white quiet zone, centred on its frame's origin."""
    cells = dictionary.markerSize + 2  # data bits plus the black border
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, cells * cell_px, borderBits=1)
    pad = _QUIET_ZONE_CELLS * cell_px
    image = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    h = size * (cells + 2 * _QUIET_ZONE_CELLS) / cells / 2.0
    corners = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    return PlanarTexture(image, corners)


def board_texture(board: cv2.aruco.CharucoBoard, px_per_square: int = 60, margin_squares: float = 0.5) -> PlanarTexture:
    """A ChArUco board on white paper, in the board's own frame (origin at the top-left chessboard corner,
    x right, y down the printed image, as OpenCV's object points are; so the printed side faces -z)."""
    cols, rows = board.getChessboardSize()
    square = board.getSquareLength()
    margin_px = round(margin_squares * px_per_square)
    image = board.generateImage(
        (cols * px_per_square + 2 * margin_px, rows * px_per_square + 2 * margin_px), marginSize=margin_px
    )
    m = margin_px / px_per_square * square
    w, h = cols * square, rows * square
    corners = np.array([[-m, -m, 0.0], [w + m, -m, 0.0], [w + m, h + m, 0.0], [-m, h + m, 0.0]])
    return PlanarTexture(image, corners, front=-1.0)


def render(
    textures: Sequence[tuple[PlanarTexture, Matrix]],
    k: NDArray[np.float64],
    size: tuple[int, int],
    background: int,
    supersample: int,
) -> NDArray[np.uint8]:
    """A grey image of the textures placed at their T_camera_plane poses (farthest first, so nearer ones cover)."""
    width, height = size
    image = np.full((height, width), background, dtype=np.uint8)
    placed = []
    for texture, t_camera_plane in textures:
        points = (t_camera_plane[:3, :3] @ texture.corners.T).T + t_camera_plane[:3, 3]
        facing = texture.front * (t_camera_plane[:3, 2] @ t_camera_plane[:3, 3]) < 0  # printed side towards camera
        if np.all(points[:, 2] > _NEAR) and facing:
            placed.append((float(points[:, 2].mean()), texture, points))
    for _, texture, points in sorted(placed, key=lambda p: -p[0]):
        _draw(image, texture.image, points, k, supersample)
    return image


def _draw(
    image: NDArray[np.uint8], texture: NDArray[np.uint8], points: NDArray[np.float64], k: NDArray[np.float64], s: int
) -> None:
    projected = (k @ points.T).T
    pixels = projected[:, :2] / projected[:, 2:3]
    height, width = image.shape
    x0, y0 = np.floor(pixels.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(pixels.max(axis=0)).astype(int) + 3
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 <= x0 or y1 <= y0:
        return
    th, tw = texture.shape
    # Supersampling is there to average the texels that fall into one pixel when the texture is minified (a
    # distant marker). A magnified texture (a marker close to the camera, hundreds of pixels wide) gains nothing
    # from it, and it cost ~10 ms a frame there: take as many sub-pixels as texels per pixel along the most
    # minified edge, at most ``s``.
    edges = np.linalg.norm(np.roll(pixels, -1, axis=0) - pixels, axis=1)
    texels = np.array([tw, th, tw, th], dtype=float)
    s = int(min(s, max(1, math.ceil(float(np.max(texels / np.maximum(edges, 1e-6)))))))
    # Pixel centres are at integer coordinates, so the texture's outer edges are at -0.5 and size - 0.5.
    source = np.float32([[-0.5, -0.5], [tw - 0.5, -0.5], [tw - 0.5, th - 0.5], [-0.5, th - 0.5]])
    to_image = cv2.getPerspectiveTransform(source, pixels.astype(np.float32))
    # Image pixel u maps to supersampled pixel s·(u − x0 + 0.5) − 0.5: the centres of the s×s sub-pixels
    # that INTER_AREA averages back into pixel u.
    to_roi = np.array([[s, 0.0, s * (0.5 - x0) - 0.5], [0.0, s, s * (0.5 - y0) - 0.5], [0.0, 0.0, 1.0]])
    roi = image[y0:y1, x0:x1]
    if s == 1:  # no sub-pixels: warp straight into the image
        cv2.warpPerspective(texture, to_roi @ to_image, (x1 - x0, y1 - y0), dst=roi, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)
        return
    big = cv2.resize(roi, ((x1 - x0) * s, (y1 - y0) * s), interpolation=cv2.INTER_NEAREST)
    cv2.warpPerspective(
        texture,
        to_roi @ to_image,
        (big.shape[1], big.shape[0]),
        dst=big,
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_TRANSPARENT,
    )
    roi[:] = cv2.resize(big, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)


def degrade(
    image: NDArray[np.uint8], blur_sigma: float, noise_sigma: float, rng: np.random.Generator
) -> NDArray[np.uint8]:
    """Lens blur then sensor noise."""
    if blur_sigma > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma)
    if noise_sigma > 0:
        noisy = image.astype(np.float32) + rng.normal(0.0, noise_sigma, image.shape).astype(np.float32)
        image = np.clip(noisy, 0, 255).astype(np.uint8)
    return image


class NoiseBank:
    """Gaussian sensor noise from fields drawn once: each frame adds one of them at a random offset (two
    saturating uint8 operations), where drawing and adding 300 000 new normal samples per frame cost ~7 ms, most
    of a 640×480 frame. A pixel's noise in two frames is independent unless both drew the same field and offset
    (1 in ``fields``·``margin``²). Noise is rounded to whole grey levels (a sensor's output is whole too)."""

    def __init__(self, size: tuple[int, int], sigma: float, rng: np.random.Generator, fields: int = 4,
                 margin: int = 64) -> None:
        width, height = size
        noise = np.rint(rng.normal(0.0, sigma, (fields, height + margin, width + margin)))
        # Kept as its positive and negative parts: image + up - down, each saturating, is clip(image + noise).
        self._up = np.clip(noise, 0, 255).astype(np.uint8)
        self._down = np.clip(-noise, 0, 255).astype(np.uint8)
        self._size, self._margin, self._rng = size, margin, rng

    def add(self, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """A new image: ``image`` plus the noise."""
        width, height = self._size
        i = int(self._rng.integers(len(self._up)))
        dy, dx = (int(v) for v in self._rng.integers(0, self._margin, 2))
        up = self._up[i, dy : dy + height, dx : dx + width]
        down = self._down[i, dy : dy + height, dx : dx + width]
        return cv2.subtract(cv2.add(image, up), down)


# A pose that moved less than this (m, and rad in the rotation's entries) renders the same picture: far below
# a pixel (~0.5 mm at 0.3 m), and above the rounding of an interpolation between two equal poses.
_SAME_POSE = 1e-9


class SyntheticCamera(CameraSource):
    """Renders what the camera sees at T_base_camera(t) for the robot pose and servo angles at capture time.

    ``robot_pose_at(t_ns)`` and ``servo_angles_at(t_ns)`` are asked at each frame's capture time, so a moving
    simulated robot is rendered where it is at that instant; no frame is delivered while either is unknown.
    Only what changed is rendered: the blurred scene is kept until the camera moves, and the sensor noise comes
    from a :class:`NoiseBank`, so a still camera's frame costs about a millisecond instead of ~12.
    """

    def __init__(
        self,
        config: SyntheticCameraConfig,
        scene: SceneConfig,
        chain: CameraChain,
        dictionary_name: str,
        robot_pose_at: Callable[[int], np.ndarray | None],
        servo_angles_at: Callable[[int], tuple[float, float] | None],
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.config = config
        self.chain = chain
        self.robot_pose_at = robot_pose_at
        self.servo_angles_at = servo_angles_at
        self.clock = clock
        self.camera_matrix = camera_matrix(config)
        self.description = f"synthetic camera {config.width}×{config.height}"
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary_name))
        self.markers = [(marker_texture(dictionary, m.id, m.size), pose_to_matrix(m.pose)) for m in scene.markers]
        rng = np.random.default_rng(config.seed)
        self._noise = NoiseBank((config.width, config.height), config.noise_sigma, rng) if config.noise_sigma > 0 else None
        self._scene: NDArray[np.uint8] | None = None  # the blurred scene without noise, as seen from _scene_pose
        self._scene_pose: Matrix | None = None
        self._count = 0
        self._next_due = time.monotonic()
        self._open = False

    @classmethod
    def from_config(
        cls,
        config: PerceptionConfig,
        robot_pose_at: Callable[[int], np.ndarray | None],
        servo_angles_at: Callable[[int], tuple[float, float] | None],
    ) -> SyntheticCamera:
        if not isinstance(config.camera, SyntheticCameraConfig):
            raise TypeError("the camera config is not a synthetic one")
        # The true mount is the configured geometry (a hand-eye file only changes what the pipeline believes).
        return cls(
            config.camera,
            config.scene,
            CameraChain(config.geometry),
            config.detector.dictionary,
            robot_pose_at,
            servo_angles_at,
        )

    def open(self) -> None:
        self._open = True
        self._next_due = time.monotonic()

    def close(self) -> None:
        self._open = False

    def interrupt(self) -> None:
        # read() waits up to pose_timeout for a pose, which stops coming when the agent shuts down first.
        self._open = False

    def read(self) -> Frame:
        """The next frame, paced at the configured frame rate.

        The scene is rendered from the robot pose at the capture time. Until that pose is known (the edge
        has just started, or the robot state stalled for longer than the pose history extrapolates) the
        camera delivers nothing, like a real camera that is not streaming yet; it fails only after
        ``pose_timeout`` s without a pose.
        """
        if not self._open:
            raise CameraError(f"{self.description} is not open")
        deadline = time.monotonic() + self.config.pose_timeout
        while True:
            self._next_due = _sleep_until(self._next_due, 1.0 / self.config.fps)
            if not self._open:
                raise CameraError(f"{self.description} was closed while waiting for a robot pose")
            frame = self._try_capture(self.clock())
            if frame is not None:
                return frame
            if time.monotonic() > deadline:
                raise CameraError(
                    f"{self.description}: no robot pose to render from for {self.config.pose_timeout:g} s "
                    "(is the robot state flowing?)"
                )

    def capture(self, t_ns: int) -> Frame:
        """Render the frame captured at ``t_ns`` (no pacing)."""
        frame = self._try_capture(t_ns)
        if frame is None:
            raise CameraError(f"{self.description}: no robot pose at the capture time to render from")
        return frame

    def _try_capture(self, t_ns: int) -> Frame | None:
        t_base_tcp = self.robot_pose_at(t_ns)
        angles = self.servo_angles_at(t_ns) if t_base_tcp is not None else None
        if t_base_tcp is None or angles is None:
            return None
        pan, tilt = angles
        t_camera_base = invert(self.chain.base_camera(t_base_tcp, pan, tilt))
        image = self.render(t_camera_base)
        frame = Frame(image, t_ns, self._count)
        self._count += 1
        return frame

    def render(self, t_camera_base: Matrix) -> NDArray[np.uint8]:
        """A new image of the scene from ``t_camera_base``, with this frame's noise."""
        c = self.config
        if self._scene_pose is None or np.max(np.abs(t_camera_base - self._scene_pose)) > _SAME_POSE:
            placed = [(texture, compose(t_camera_base, t_base_marker)) for texture, t_base_marker in self.markers]
            scene = render(placed, self.camera_matrix, (c.width, c.height), c.background, c.supersample)
            self._scene = cv2.GaussianBlur(scene, (0, 0), c.blur_sigma) if c.blur_sigma > 0 else scene
            self._scene_pose = np.array(t_camera_base)
        assert self._scene is not None
        # Always a new array: consumers tell frames apart by identity (the video stream's shared source).
        return self._noise.add(self._scene) if self._noise is not None else self._scene.copy()


@dataclass
class BoardView:
    image: NDArray[np.uint8]
    t_base_tcp: Matrix  # the robot pose as the robot would report it (with its noise)
    t_camera_board: Matrix  # ground truth


def board_pose_in_base(board: cv2.aruco.CharucoBoard, centre: NDArray[np.float64]) -> Matrix:
    """T_base_board for a board lying face up with its centre at ``centre``."""
    cols, rows = board.getChessboardSize()
    half = np.array([cols, rows, 0.0]) * board.getSquareLength() / 2.0
    flipped = make_transform(rotvec_to_matrix([math.pi, 0.0, 0.0]))  # printed side (-z) up
    return compose(make_transform(None, centre), flipped, make_transform(None, -half))


def render_board_views(
    board: cv2.aruco.CharucoBoard,
    camera: SyntheticCameraConfig,
    tcp_camera: Matrix,
    count: int,
    rng: np.random.Generator,
    robot_noise: tuple[float, float] = (0.0, 0.0),
) -> tuple[list[BoardView], Matrix]:
    """``count`` views of a board lying in the base frame, each from a different robot pose, with the camera
    at ``tcp_camera`` on the TCP. ``robot_noise`` is (m, rad) of Gaussian error on the reported robot poses.
    Returns the views and T_base_board."""
    centre = np.array([0.45, 0.0, 0.0])
    t_base_board = board_pose_in_base(board, centre)
    texture = board_texture(board)
    k = camera_matrix(camera)
    views = []
    for _ in range(count):
        polar = math.radians(rng.uniform(12.0, 40.0))
        azimuth = rng.uniform(-math.pi, math.pi)
        distance = rng.uniform(0.30, 0.42)
        eye = centre + distance * np.array(
            [math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth), math.cos(polar)]
        )
        aim = centre + np.append(rng.uniform(-0.02, 0.02, 2), 0.0)
        t_base_camera = look_at(eye, aim, roll=rng.uniform(-0.6, 0.6))
        t_base_tcp = compose(t_base_camera, invert(tcp_camera))
        t_camera_board = compose(invert(t_base_camera), t_base_board)
        image = render(
            [(texture, t_camera_board)], k, (camera.width, camera.height), camera.background, camera.supersample
        )
        image = degrade(image, camera.blur_sigma, camera.noise_sigma, rng)
        reported = compose(
            t_base_tcp,
            make_transform(rotvec_to_matrix(rng.normal(0.0, robot_noise[1], 3)), rng.normal(0.0, robot_noise[0], 3)),
        )
        views.append(BoardView(image, reported, t_camera_board))
    return views, t_base_board


def look_at(eye: NDArray[np.float64], target: NDArray[np.float64], roll: float) -> Matrix:
    """T_base_camera of an OpenCV camera at ``eye`` looking at ``target``, rolled by ``roll`` rad about its
    optical axis (for planning and rendering views)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]) @ rotvec_to_matrix([0.0, 0.0, roll]), eye)
