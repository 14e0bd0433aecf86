"""The survey flight: a double lawnmower grid at 50, 40 and 30 m with nadir and oblique views.

Drone convention: pitch -90 deg looks straight down (nadir), -75 / -70 deg are oblique views
tilted forward along the flight direction (heading). The image's top edge points along the
heading. Line and station spacing come from the overlaps at the 50 m reference altitude and
are kept at every altitude (lower flights therefore overlap less, as in real surveys flown
with one plan).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from occufly.camera import Camera, look_at
from occufly.synthetic.presets import Preset
from occufly.synthetic.world import World

PITCHES = (-90.0, -75.0, -70.0)
REFERENCE_ALTITUDE = 50.0


@dataclass
class PlannedFrame:
    """One image of the flight.

    center: (3,) float64 scene-local metres; T_cam_world: (4, 4) float64 local world-to-camera.
    """

    name: str
    center: np.ndarray
    T_cam_world: np.ndarray
    nominal_altitude: int
    altitude_above_ground: float
    pitch_deg: float
    heading_deg: float
    pass_index: int  # 0 = lines along x, 1 = lines along y
    line: int
    station: int


def make_camera(preset: Preset) -> Camera:
    """PINHOLE camera with ``preset.hfov_deg`` horizontal field of view, principal point centred."""
    f = (preset.width / 2) / math.tan(math.radians(preset.hfov_deg) / 2)
    return Camera("PINHOLE", preset.width, preset.height, [f, f, preset.width / 2, preset.height / 2])


def footprint(camera: Camera, altitude: float) -> tuple[float, float]:
    """(across-track, along-track) ground size in metres of a nadir image at ``altitude``."""
    fx, fy = camera.focal
    return camera.width / fx * altitude, camera.height / fy * altitude


def _spacing(span: float, step: float) -> np.ndarray:
    n = max(2, int(math.ceil(span / step)) + 1)
    return np.linspace(0.0, span, n)


def plan_flight(preset: Preset, world: World, camera: Camera) -> list[PlannedFrame]:
    across, along = footprint(camera, REFERENCE_ALTITUDE)
    line_pos = _spacing(preset.core, (1 - preset.side_overlap) * across)
    station_pos = _spacing(preset.core, (1 - preset.forward_overlap) * along)
    core_xy = np.linspace(0, preset.core, 9)
    X, Y = np.meshgrid(core_xy, core_xy)
    z_ref = float(np.median(world.ground_z(X.ravel(), Y.ravel())))  # take-off height
    frames: list[PlannedFrame] = []
    for a_idx, alt in enumerate(preset.altitudes):
        for pass_index in (0, 1):
            for li, lp in enumerate(line_pos):
                forward = li % 2 == 0  # lawnmower: every other line flown backwards
                stations = station_pos if forward else station_pos[::-1]
                sign = 1.0 if forward else -1.0
                heading = np.array([sign, 0.0, 0.0]) if pass_index == 0 else np.array([0.0, sign, 0.0])
                for si, sp in enumerate(stations):
                    x, y = (sp, lp) if pass_index == 0 else (lp, sp)
                    center = np.array([x, y, z_ref + alt])
                    pitch = PITCHES[(li + si + a_idx) % len(PITCHES)]
                    p = math.radians(pitch)
                    view = np.array([math.cos(p) * heading[0], math.cos(p) * heading[1], math.sin(p)])
                    T = look_at(center, center + view, up=heading)
                    ground = float(world.ground_z(np.array([x]), np.array([y]))[0])
                    frames.append(
                        PlannedFrame(
                            name=f"frame_{len(frames):06d}{preset.image_ext}",
                            center=center,
                            T_cam_world=T,
                            nominal_altitude=int(alt),
                            altitude_above_ground=float(center[2] - ground),
                            pitch_deg=pitch,
                            heading_deg=float(math.degrees(math.atan2(heading[1], heading[0]))),
                            pass_index=pass_index,
                            line=li,
                            station=si,
                        )
                    )
    return frames
