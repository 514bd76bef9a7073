"""Simulated camera: an object with ``cv2.VideoCapture``'s methods that renders the DEM's scene.

Frames are rendered by :func:`appliance.vision.synth.render_photo_from` from the world's true
position (followed when the platform moves, as a rover does between stops) and the head's pose
(stage heading, tilt).  Properties behave as a V4L2 driver's: width
and height must equal the intrinsics' (other sizes are refused), exposure scales the brightness.
Faults: ``unplug()`` makes ``grab``/``read`` fail; ``refuse`` lists properties whose ``set`` fails;
``unplug_after`` unplugs after that many frames read; ``black_frames`` lists read numbers (from 0)
that return a black frame (lens cap, dead sensor).  ``weather`` (:mod:`appliance.sim.weather`) renders the frames
under that weather instead of the plain scene, its clouds drifting from one frame read to the next.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from appliance.sim.weather import WeatherScene, render_weather_photo
from appliance.sim.world import SimWorld
from appliance.vision.camera import CameraPose
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.synth import SkylineFn, dem_skyline_fn, render_photo_from

NOMINAL_EXPOSURE = 100.0


class SimVideoCapture:
    def __init__(
        self,
        world: SimWorld,
        intrinsics: CameraIntrinsics,
        skyline_fn: SkylineFn | None = None,
        dem: Any = None,
        seed: int = 0,
        refuse: frozenset[int] = frozenset(),
        unplug_after: int | None = None,
        black_frames: frozenset[int] = frozenset(),
        weather: WeatherScene | None = None,
    ) -> None:
        if skyline_fn is None and dem is None:
            raise ValueError("SimVideoCapture needs a DEM or a skyline function")
        self.world, self.intrinsics, self.dem = world, intrinsics, dem
        self._fixed_skyline_fn = skyline_fn
        self._where: tuple[float, float, float] | None = None
        self._dem_skyline_fn: SkylineFn | None = None
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.refuse = set(refuse)
        self.unplug_after, self.black_frames = unplug_after, frozenset(black_frames)
        self.weather = weather
        self.opened = True
        self.frames = 0
        self.props: dict[int, float] = {
            cv2.CAP_PROP_FRAME_WIDTH: float(intrinsics.width),
            cv2.CAP_PROP_FRAME_HEIGHT: float(intrinsics.height),
            cv2.CAP_PROP_AUTO_EXPOSURE: 3.0,
            cv2.CAP_PROP_EXPOSURE: NOMINAL_EXPOSURE,
            cv2.CAP_PROP_GAIN: 0.0,
            cv2.CAP_PROP_BUFFERSIZE: 4.0,
        }

    @property
    def skyline_fn(self) -> SkylineFn:
        """The skyline function given, else the DEM's skyline seen from where the world is now."""
        if self._fixed_skyline_fn is not None:
            return self._fixed_skyline_fn
        w = self.world
        where = (w.lat_deg, w.lon_deg, w.mast_height_m)
        if self._dem_skyline_fn is None or where != self._where:
            self._dem_skyline_fn = dem_skyline_fn(self.dem, *where)
            self._where = where
        return self._dem_skyline_fn

    def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        if not self.opened or prop in self.refuse or prop not in self.props:
            return False
        if prop == cv2.CAP_PROP_FRAME_WIDTH and value != self.intrinsics.width:
            return False
        if prop == cv2.CAP_PROP_FRAME_HEIGHT and value != self.intrinsics.height:
            return False
        self.props[prop] = float(value)
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        return self.opened

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self.unplug_after is not None and self.frames >= self.unplug_after:
            self.opened = False
        if not self.opened:
            return False, None
        if self.frames in self.black_frames:
            self.frames += 1
            return True, np.zeros((self.intrinsics.height, self.intrinsics.width, 3), np.uint8)
        pitch, roll = self.world.head_tilt()
        pose = CameraPose(self.world.head_heading_deg, pitch, roll)
        if self.weather is not None:
            img = render_weather_photo(self.skyline_fn, pose, self.intrinsics, self.rng, self.weather, self.frames)
        else:
            img = render_photo_from(self.skyline_fn, pose, self.intrinsics, self.rng, scene_seed=self.seed)
        gain = self.props[cv2.CAP_PROP_EXPOSURE] / NOMINAL_EXPOSURE
        if gain != 1.0:
            img = np.clip(img.astype(np.float32) * gain, 0, 255).astype(np.uint8)
        self.frames += 1
        return True, img

    def unplug(self) -> None:
        self.opened = False

    def release(self) -> None:
        self.opened = False
