"""The scene family: named presets, each a seeded recipe for a :class:`~data_modules.synthetic.scene.Scene`
plus the sensor settings it calls for (on top of :class:`~data_modules.synthetic.sensor.SensorModel`'s
Kinect-like defaults).

``cube`` is the original fixed moving-cube scene (the seed does not change it); every other preset
draws its room, furniture, textures, object shapes, sizes, speeds and phases from the seed, within the
ranges its recipe names, so the property in its name holds for every seed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from data_modules.synthetic.layout import (
    KeepOut,
    footprint_radius,
    random_furniture,
    random_room,
    random_shape,
    swept_xy,
)
from data_modules.synthetic.motion import (
    Breathe,
    CircleCurve,
    Fixed,
    Hinge,
    LookAtCamera,
    Motion,
    Orbit,
    Shake,
    SineCurve,
    Slide,
    StopGo,
    Wobble,
    YawTarget,
)
from data_modules.synthetic.scene import Room, Scene, SceneObject
from data_modules.synthetic.shapes import Box, Cylinder, Shape, Sphere, bound_half
from data_modules.synthetic.textures import Texture, random_texture

__all__ = ["PRESETS", "Preset", "build_scene"]

_SWEEP_S = 60.0  # seconds of motion sampled for keep-out zones (every motion here is periodic)


@dataclass(frozen=True)
class Preset:
    build: Callable[[int], Scene]
    summary: str
    sensor: dict[str, object] = field(default_factory=dict)


def build_scene(name: str, seed: int) -> Scene:
    """The scene of preset ``name`` for layout seed ``seed`` (KeyError for an unknown name)."""
    return PRESETS[name].build(int(seed))


# ------------------------------------------------------------------------------------------- cube


def _tex(salt: int, a: tuple, b: tuple, c: tuple, d: tuple) -> Texture:
    return Texture(salt, a, b, c, d)


def _cube(seed: int) -> Scene:
    """The original moving-cube scene, value for value."""
    room = Room((-2.0, -1.5, 0.0), (2.0, 1.5, 2.6), (
        _tex(11, (0.62, 0.55, 0.48), (0.30, 0.28, 0.25), (1.3, 1.1, 0.9), (0.00, 0.12, 0.27)),
        _tex(13, (0.55, 0.58, 0.50), (0.28, 0.30, 0.26), (1.1, 1.3, 0.8), (0.45, 0.30, 0.10)),
        _tex(17, (0.60, 0.52, 0.55), (0.30, 0.25, 0.28), (0.9, 1.2, 1.4), (0.20, 0.55, 0.35)),
        _tex(19, (0.50, 0.56, 0.60), (0.26, 0.28, 0.30), (1.2, 0.9, 1.1), (0.70, 0.15, 0.45)),
        _tex(29, (0.52, 0.50, 0.47), (0.28, 0.27, 0.26), (1.0, 1.0, 1.3), (0.35, 0.60, 0.80)),
        _tex(31, (0.66, 0.64, 0.60), (0.22, 0.22, 0.24), (1.4, 1.2, 1.0), (0.05, 0.25, 0.50))))
    statics = (
        SceneObject("box_a", Box((0.35, 0.25, 0.25)), _tex(23, (0.45, 0.55, 0.40), (0.35, 0.30, 0.30), (1.0, 1.4, 1.1), (0.30, 0.20, 0.60)),
                    Fixed((-1.05, 0.75, 0.25), math.radians(20.0))),
        SceneObject("box_b", Box((0.20, 0.20, 0.40)), _tex(37, (0.40, 0.45, 0.62), (0.30, 0.32, 0.35), (1.2, 0.8, 1.5), (0.55, 0.35, 0.10)),
                    Fixed((1.15, 0.85, 0.40), math.radians(-15.0))),
        SceneObject("sphere", Sphere(0.22), _tex(41, (0.58, 0.44, 0.56), (0.35, 0.30, 0.35), (0.9, 1.3, 1.0), (0.10, 0.70, 0.40)),
                    Fixed((0.30, 1.05, 0.22))),
    )
    cube = SceneObject("cube", Box((0.18, 0.18, 0.18)), _tex(53, (0.70, 0.42, 0.22), (0.30, 0.35, 0.22), (1.6, 1.0, 1.3), (0.00, 0.33, 0.67)),
                       Wobble((0.0, 0.25, 1.0), (0.45, 0.10, 0.12), (0.35, 0.5, 0.8), (-0.9, 0.0, 0.0), yaw0=0.35, yaw_rate=0.25,
                              pitch0=0.2, pitch_amp=0.25, pitch_freq=0.40, roll_amp=0.15, roll_freq=0.3))
    camera = LookAtCamera(SineCurve((0.0, -1.0, 1.35), (0.70, 0.22, 0.10), (0.45, 0.31, 0.53), (-1.0, 0.4, 0.2)),
                          SineCurve((0.0, 0.45, 0.85), (0.12, 0.0, 0.05), (0.21, 0.0, 0.37), (0.5, 0.0, 0.0)), Shake(1.0))
    return Scene(room, statics, (cube,), camera, "moving cube: fixed room, 2 boxes + sphere, one tumbling cube")


# --------------------------------------------------------------------------------- shared recipes


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return round(float(rng.uniform(lo, hi)), 4)


def _handheld(rng: np.random.Generator, room: Room, arc: float = 0.5, shake: float = 1.0,
              target: tuple[float, float, float] = (0.0, 0.3, 0.7)) -> LookAtCamera:
    """A slow hand-held arc 0.7 m in front of the -y wall, looking at ``target`` (+ a slow drift)."""
    ph = tuple(_u(rng, -math.pi, math.pi) for _ in range(3))
    position = SineCurve((0.0, room.lo[1] + 0.75, _u(rng, 1.3, 1.5)), (arc, 0.12, 0.08), (0.40, 0.31, 0.53), ph)
    look = SineCurve(target, (0.12, 0.0, 0.05), (0.21, 0.0, 0.37), (ph[0], 0.0, 0.0))
    return LookAtCamera(position, look, Shake(shake))


def _sightlines(camera: LookAtCamera, mover: SceneObject, duration: float, step: float = 0.25) -> np.ndarray:
    """(M, 2) floor-plane points on the segments from the camera to the mover at the same instants."""
    pts = []
    for t in np.arange(0.0, duration, step):
        a, b = camera.pose(float(t))[:2, 3], mover.motion.pose(float(t))[:2, 3]
        pts.append(a + np.linspace(0.0, 1.0, 12)[:, None] * (b - a))
    return np.concatenate(pts)


def _keep_out(camera: LookAtCamera, movers: tuple[SceneObject, ...]) -> list[KeepOut]:
    """Floor-plane zones furniture must avoid: the camera path, every mover's swept path and the lines
    of sight between them (so furniture never hides a moving object)."""
    zones: list[KeepOut] = [(swept_xy(camera.pose, _SWEEP_S, 0.1), 0.5)]
    for m in movers:
        zones += [(swept_xy(m.motion.pose, _SWEEP_S, 0.1), footprint_radius(m.shape) + 0.1),
                  (_sightlines(camera, m, _SWEEP_S), footprint_radius(m.shape))]
    return zones


def _mover(rng: np.random.Generator, name: str, shape: Shape, motion: Motion) -> SceneObject:
    return SceneObject(name, shape, random_texture(rng, "object"), motion)


def _finish(rng: np.random.Generator, room: Room, camera: LookAtCamera, movers: tuple[SceneObject, ...], description: str,
            furniture: int | None = None, extra: tuple[SceneObject, ...] = ()) -> Scene:
    count = int(rng.integers(4, 8)) if furniture is None else furniture
    statics = extra + random_furniture(rng, room, count, _keep_out(camera, movers))
    return Scene(room, statics, movers, camera, description)


# ----------------------------------------------------------------------------------- the family


def _big_fast(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 101])
    room = random_room(rng, half_x=(2.5, 3.0))
    box = Box((_u(rng, 0.3, 0.4), _u(rng, 0.22, 0.3), _u(rng, 0.22, 0.3)))
    a, y, z = _u(rng, 1.0, 1.2), _u(rng, 0.2, 0.5), _u(rng, 0.6, 0.8)
    motion = Slide((-a, y, z), (a, y, z), period=_u(rng, 2.4, 3.0), phase=_u(rng, 0.0, 3.0), yaw_rate=_u(rng, 0.8, 1.2))
    camera = _handheld(rng, room, arc=0.3, target=(0.0, 0.3, 0.6))
    return _finish(rng, room, camera, (_mover(rng, "big_box", box, motion),),
                   "a 0.6-0.8 m box sliding across the view at up to 2.5-3 m/s")


def _crossing(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 102])
    room = random_room(rng)
    a, period = _u(rng, 1.0, 1.2), _u(rng, 4.0, 5.0)
    y_far, y_near, z_near = _u(rng, 0.7, 0.9), _u(rng, -0.1, 0.0), _u(rng, 0.55, 0.7)
    # Same period and phase: far goes -a -> a while near goes a -> -a, so they pass x = 0 together.
    far = _mover(rng, "far", random_shape(rng, _u(rng, 0.2, 0.28), ("box", "cylinder")),
                 Slide((-a, y_far, 0.6), (a, y_far, 0.6), period, yaw_rate=_u(rng, 0.3, 0.6)))
    near = _mover(rng, "near", random_shape(rng, _u(rng, 0.14, 0.2), ("sphere", "box")),
                  Slide((a, y_near, z_near), (-a, y_near, z_near), period, yaw_rate=_u(rng, -0.6, -0.3)))
    camera = _handheld(rng, room, arc=0.15, target=(0.0, 0.4, 0.6))
    return _finish(rng, room, camera, (far, near), "two objects in opposite directions on lanes at different depths, crossing mid-view")


def _static_room(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 103])
    room = random_room(rng)
    pos = (_u(rng, -0.3, 0.3), room.lo[1] + 0.75, _u(rng, 1.3, 1.5))
    target = YawTarget(pos, math.pi / 2, distance=2.0, drop=0.6, sweep=_u(rng, 0.5, 0.7), sweep_freq=_u(rng, 0.7, 0.9))
    camera = LookAtCamera(SineCurve(pos), target, Shake(1.5))
    return _finish(rng, room, camera, (), "static room only, hand-held pan", furniture=int(rng.integers(6, 10)))


def _stop_and_go(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 104])
    room = random_room(rng)
    shape = random_shape(rng, _u(rng, 0.2, 0.28), ("box", "cylinder"))
    hz = float(bound_half(shape)[2])
    a, y = _u(rng, 0.8, 1.1), _u(rng, 0.2, 0.5)
    motion = StopGo((-a, y, hz), (a, y, hz), stop=_u(rng, 0.8, 1.2), move=_u(rng, 1.0, 1.4), turn=_u(rng, 0.5, 1.5))
    camera = _handheld(rng, room, arc=0.4, target=(0.0, 0.3, 0.4))
    return _finish(rng, room, camera, (_mover(rng, "pushed", shape, motion),),
                   "an object on the floor that rests, slides across, rests and slides back")


def _orbit_ball(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 105])
    room = random_room(rng, half_x=(2.8, 3.2), half_y=(2.7, 3.0))
    r_cam = _u(rng, 1.6, 1.9)
    camera = LookAtCamera(CircleCurve((0.0, 0.0, _u(rng, 1.3, 1.5)), r_cam, _u(rng, 0.25, 0.35), phase=-math.pi / 2, bob=0.05, bob_freq=0.7),
                          SineCurve((0.0, 0.0, 0.4)), Shake(0.5))
    radius = _u(rng, 0.15, 0.22)
    ball = _mover(rng, "ball", Sphere(radius), Orbit((0.0, 0.0, radius), _u(rng, 0.55, 0.7), -_u(rng, 1.0, 1.5), phase=_u(rng, 0, 6.28)))
    pedestal = SceneObject("pedestal", Cylinder(0.2, (hh := _u(rng, 0.2, 0.4))), random_texture(rng, "object"), Fixed((0.0, 0.0, hh)))
    return _finish(rng, room, camera, (ball,), "camera orbits the room centre; a ball circles a pedestal the other way",
                   extra=(pedestal,))


def _fast_turn(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 106])
    room = random_room(rng, half_x=(2.6, 3.0))
    pos = (0.0, room.lo[1] + 0.8, _u(rng, 1.4, 1.6))
    turn = _u(rng, 1.2, 1.6)
    target = YawTarget(pos, math.pi / 2 - turn / 2, distance=2.0, drop=0.7, turn=turn, hold=_u(rng, 1.0, 1.4), turn_time=_u(rng, 0.5, 0.7))
    camera = LookAtCamera(SineCurve(pos), target, Shake(1.0))
    spinner = random_shape(rng, _u(rng, 0.2, 0.25), ("box", "cylinder"))
    turning = _mover(rng, "turning", spinner, Orbit((-0.7, 0.6, float(bound_half(spinner)[2])), 0.0, 0.0, spin=_u(rng, 1.5, 2.5)))
    x = room.hi[0] - 0.5
    passing = _mover(rng, "passing", random_shape(rng, _u(rng, 0.15, 0.2)),
                     Slide((-x, 1.1, 0.9), (x, 1.1, 0.9), period=_u(rng, 6.0, 8.0), phase=_u(rng, 0, 2.0), profile="linear"))
    return _finish(rng, room, camera, (turning, passing),
                   "camera at rest whipping 70-90 degrees back and forth; an object turns in place, another passes through")


def _three_objects(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 107])
    room = random_room(rng, half_x=(2.6, 3.0), half_y=(2.2, 2.6))
    slide_shape = random_shape(rng, _u(rng, 0.15, 0.22))
    slider = _mover(rng, "slider", slide_shape, Slide((-1.1, 1.0, 0.7), (1.1, 1.0, 0.7), period=_u(rng, 3.0, 4.0), yaw_rate=0.5))
    spin_shape = random_shape(rng, _u(rng, 0.2, 0.3), ("box", "cylinder"))
    spinner = _mover(rng, "spinner", spin_shape, Orbit((0.8, 0.1, float(bound_half(spin_shape)[2])), 0.0, 0.0, spin=_u(rng, -1.5, -0.8)))
    ball_r = _u(rng, 0.1, 0.14)
    circler = _mover(rng, "circler", Sphere(ball_r), Orbit((-0.7, 0.0, 0.6), 0.35, _u(rng, 1.5, 2.2), bob=0.15, bob_freq=2.0))
    camera = _handheld(rng, room, arc=0.4, shake=2.5, target=(0.0, 0.4, 0.6))
    return _finish(rng, room, camera, (slider, spinner, circler),
                   "three objects: a slider, a spinner on the floor and a bobbing ball circling; shaky hand-held camera")


def _door(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 108])
    room = random_room(rng)
    half = (_u(rng, 0.3, 0.36), 0.02, _u(rng, 0.42, 0.5))  # 0.6-0.72 m wide, 4 cm thin, 0.84-1.0 m tall
    hinge = (_u(rng, -0.6, -0.4), _u(rng, 0.6, 0.9), half[2] + 0.01)
    swing = Hinge(hinge, half[0] + 0.01, yaw0=_u(rng, -0.2, 0.0), amplitude=_u(rng, 1.2, 1.5), freq=_u(rng, 1.2, 1.8))
    camera = _handheld(rng, room, arc=0.3, target=(0.0, 0.5, 0.5))
    return _finish(rng, room, camera, (_mover(rng, "door", Box(half), swing),),
                   "a thin (4 cm) door swinging 70-85 degrees on a vertical hinge and back")


def _breathing(seed: int) -> Scene:
    rng = np.random.default_rng([seed, 109])
    room = random_room(rng)
    drift = Orbit((0.0, _u(rng, 0.5, 0.7), _u(rng, 0.6, 0.7)), _u(rng, 0.15, 0.25), _u(rng, 0.3, 0.5), phase=_u(rng, 0.0, 6.28))
    blob = _mover(rng, "blob", Sphere(_u(rng, 0.2, 0.25)), Breathe(drift, depth=_u(rng, 0.3, 0.4), freq=_u(rng, 2.0, 3.0)))
    camera = _handheld(rng, room, arc=0.3, target=(0.0, 0.4, 0.6))
    return _finish(rng, room, camera, (blob,), "a floating ball whose radius breathes by 30-40 % (non-rigid) while it drifts on a slow circle")


PRESETS: dict[str, Preset] = {
    "cube": Preset(_cube, "the original scene: one tumbling cube, slow hand-held arc"),
    "big_fast": Preset(_big_fast, "large box sliding fast across the view, hand-held arc"),
    "crossing": Preset(_crossing, "two objects crossing in view at different depths, near-static hand-held camera"),
    "static_room": Preset(_static_room, "no moving objects, hand-held pan"),
    "stop_and_go": Preset(_stop_and_go, "object on the floor that rests and moves in turns, hand-held arc"),
    "orbit_ball": Preset(_orbit_ball, "camera orbiting, ball circling a pedestal"),
    "fast_turn": Preset(_fast_turn, "fast camera turns with motion blur and exposure drift; turning + passing objects",
                        {"motion_blur": 5, "exposure": 0.15}),
    "three_objects": Preset(_three_objects, "slider, spinner, circling ball; shaky camera, lateral noise, mm depth steps",
                            {"lateral": 0.7, "quantization": 0.001}),
    "door": Preset(_door, "thin articulated object: a door swinging on its hinge, hand-held arc"),
    "breathing": Preset(_breathing, "non-rigid object: a drifting ball whose radius breathes, hand-held arc"),
}
