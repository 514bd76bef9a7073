"""The simulated platform: one :class:`SimWorld`, its twins started, and the real drivers on them.

Serial twins (GPS, PTU, NMEA compass) get a pty each under a private temporary folder
(:class:`appliance.sim.scratch.SimFolder`, removed on close and after a kill); the I2C
twins (HMC5883L, ADXL345) sit on one :class:`FakeI2cBus`; the camera is a :class:`SimVideoCapture`
driven by the real :class:`V4l2Camera` driver; the leveller is the person at the tripod
(:class:`SimLeveller`).  For a traverse (``[traverse] stops``), the rover (:class:`RoverTwin`) sends its
odometry over a pty too and drives the world between stops; with ``[devices.odometry] kind = "mavlink"``
the autopilot twin (:class:`AutopilotTwin`) follows it and speaks MAVLink over UDP to the real link.
Faults come from ``[sim.faults]``.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from appliance.config import Config, OdometryKind, SimConfig
from appliance.drivers.accelerometer import TiltOffset
from appliance.drivers.camera import V4l2Camera
from appliance.drivers.factory import DeviceCalibration, Devices, build_devices, uses_nmea_compass
from appliance.drivers.magnetometer import HardSoftIron
from appliance.errors import ConfigError
from appliance.sim.camera_twin import SimVideoCapture
from appliance.sim.i2c_chips import FakeI2cBus, SimAdxl345, SimHmc5883l
from appliance.sim.leveller import SimLeveller
from appliance.sim.nmea_twins import GpsTwin, NmeaCompassTwin
from appliance.sim.ptu_twin import PtuTwin
from appliance.sim.pty_port import PtyPort
from appliance.sim.rover_twin import RoverTwin
from appliance.sim.scratch import SimFolder
from appliance.sim.world import SimClock, SimWorld
from appliance.terrain.dem import load_dem
from appliance.vision.intrinsics import CameraIntrinsics, load_intrinsics

if TYPE_CHECKING:
    from appliance.sim.autopilot_twin import AutopilotTwin

log = logging.getLogger(__name__)


def make_world(sim: SimConfig, dem: object | None = None) -> SimWorld:
    try:
        start = dt.datetime.fromisoformat(sim.start_utc.replace("Z", "+00:00"))
    except ValueError:
        raise ConfigError(f"sim.start_utc: not an ISO 8601 time: {sim.start_utc!r}") from None
    ground = sim.ground_elevation_m
    if ground is None:
        if dem is None:
            raise ConfigError("sim.ground_elevation_m: needed when no DEM is loaded")
        ground = float(dem.sample_lonlat(sim.lon_deg, sim.lat_deg))  # type: ignore[attr-defined]
        if not math.isfinite(ground):
            raise ConfigError(f"sim: position {sim.lat_deg}, {sim.lon_deg} is outside the DEM {sim.dem!r}")
    return SimWorld(sim.lat_deg, sim.lon_deg, ground, sim.mast_height_m, sim.geoid_separation_m, sim.heading_deg,
                    sim.tilt_north_deg, sim.tilt_east_deg, sim.hard_iron_t, sim.soft_iron,
                    SimClock(start, sim.time_rate))


def open_sim_platform(config: Config, with_camera: bool = True,
                      calibration: DeviceCalibration | None = None,
                      on_map: Callable[[float, float], bool] | None = None) -> Devices:
    """The twins of ``[sim]`` started and the real drivers on them; ``calibration`` defaults to the
    inline values of ``[devices.compass]`` and ``[devices.inclinometer]``.  With ``[traverse] stops``,
    the rover twin too (``devices.rover``), whose legs end where ``on_map(lat, lon)`` (default: on
    the DEM's terrain)."""
    sim = config.sim
    if calibration is None:
        c, i = config.devices.compass, config.devices.inclinometer
        calibration = DeviceCalibration(HardSoftIron(c.hard_iron_offset, c.soft_iron_matrix),
                                        TiltOffset(i.pitch_offset_deg, i.roll_offset_deg))
    dem = None
    if with_camera or sim.ground_elevation_m is None:
        dem = load_dem(sim.dem)
    world = make_world(sim, dem)
    scratch = SimFolder()
    stops: list = []
    try:
        return _start_twins(config, world, dem, stops, scratch, with_camera, calibration, on_map)
    except BaseException:
        for s in reversed(stops):
            s()
        scratch.remove()
        raise


def _start_twins(config: Config, world: SimWorld, dem: object | None, stops: list, scratch: SimFolder,
                 with_camera: bool, calibration: DeviceCalibration,
                 on_map: Callable[[float, float], bool] | None) -> Devices:
    sim, faults, folder = config.sim, config.sim.faults, scratch.path
    gps_port = PtyPort(folder / "gps")
    gps_twin = GpsTwin(world, gps_port, sim, faults)
    ptu_port = PtyPort(folder / "ptu")
    ptu_twin = PtuTwin(world, ptu_port, min_position=-7000, max_position=7000,
                       miss_step_every=faults.stage_miss_step_every, miss_positions=faults.stage_miss_positions,
                       stall_at_deg=faults.stage_stall_at_deg)
    compass_src = ""
    if uses_nmea_compass(config):
        c_port = PtyPort(folder / "compass")
        c_twin = NmeaCompassTwin(world, c_port)
        c_twin.start()
        stops += [c_twin.stop, c_port.close]
        compass_src = str(c_port.path)
    gps_twin.start()
    ptu_twin.start()
    stops += [gps_twin.stop, gps_port.close, ptu_twin.stop, ptu_port.close]
    bus = FakeI2cBus()
    bus.attach(config.devices.compass.i2c_address,
               SimHmc5883l(world, seed=sim.seed, stuck=faults.compass_stuck,
                           drift_deg_per_s=faults.compass_drift_deg_per_s,
                           metal_nearby=faults.compass_metal_nearby))
    if not faults.inclinometer_absent:
        bus.attach(config.devices.inclinometer.i2c_address,
                   SimAdxl345(world, seed=sim.seed, stuck=faults.inclinometer_stuck))
    camera = None
    if with_camera:
        cam_cfg = config.devices.camera
        intr = (load_intrinsics(cam_cfg.intrinsics_file) if cam_cfg.intrinsics_file is not None
                else CameraIntrinsics.from_fov(cam_cfg.width, cam_cfg.height, 60.0))
        black = frozenset(faults.camera_black_frames)

        def video_capture(*_: object) -> SimVideoCapture:
            return SimVideoCapture(world, intr, dem=dem, seed=sim.seed, unplug_after=faults.camera_unplug_after,
                                   black_frames=black)

        camera = V4l2Camera(cam_cfg, intr, video_capture, world.clock.now_ns)
    rover, odometry_src = None, ""
    if config.traverse.stops:
        if dem is None:
            dem = load_dem(sim.dem)
        odo_port = PtyPort(folder / "odometry")
        stops.append(odo_port.close)

        def ground_m(lat: float, lon: float) -> float:
            return float(dem.sample_lonlat(lon, lat))  # type: ignore[attr-defined]

        rover = RoverTwin(world, odo_port, sim, ground_m, on_map or (lambda lat, lon: True), sim.seed + 1)
        odometry_src = str(odo_port.path)
        if config.devices.odometry.kind is OdometryKind.MAVLINK:
            odometry_src = "udpin:127.0.0.1:0"  # a port of the system's choosing, told to the autopilot twin
    devices = build_devices(config, str(gps_port.path), str(ptu_port.path), compass_src, bus, camera,
                            world.clock, calibration, odometry_src)
    devices.leveller = SimLeveller(world)
    devices._closers[:0] = [scratch.remove, *stops]
    devices.world = world  # type: ignore[attr-defined]
    devices.rover = rover  # type: ignore[attr-defined]
    if rover is not None and devices.autopilot is not None:
        # pymavlink (an optional library) loads only for a MAVLink rover
        from appliance.sim.autopilot_twin import MavlinkRover

        devices.rover = MavlinkRover(rover, start_autopilot_twin(world, sim, devices),  # type: ignore[attr-defined]
                                     sim.faults.autopilot_reboot_leg)
    return devices


def start_autopilot_twin(world: SimWorld, sim: SimConfig, devices: Devices) -> AutopilotTwin:
    """The autopilot twin sending to the MAVLink link's UDP port, its drift per metre the rover twin's
    odometry sigma over the mean leg; stopped after the drivers when the devices close."""
    # pymavlink (an optional library) loads only for a MAVLink rover
    from appliance.sim.autopilot_twin import AutopilotTwin, UdpTwinLink

    assert devices.autopilot is not None and devices.autopilot.udp_port is not None
    mean_leg_m = 0.5 * (sim.leg_length_m[0] + sim.leg_length_m[1])
    drift = sim.odometry_sigma_m / mean_leg_m if mean_leg_m > 0 else 0.0
    o = devices.autopilot.cfg
    twin = AutopilotTwin(world, UdpTwinLink(("127.0.0.1", devices.autopilot.udp_port)), sim.seed + 2, drift,
                         system_id=o.system_id, component_id=o.component_id or 1)
    twin.start()
    devices._closers.insert(0, twin.stop)
    devices.autopilot_twin = twin  # type: ignore[attr-defined]
    return twin
