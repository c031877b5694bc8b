"""Synthetic MetaRoom: the paper's room, table and 20 indoor object classes as point clouds.

World frame: z up, metres, origin at the centre of the table top, so objects stand on z = 0
and their centres sit about 0.1 m above the origin, where the cameras look (docs/method.md §3).
The room spans x, y in [-3, 3] with the floor at z = -1 (the table is 1 m high) and the
ceiling 3.7 m above the floor. Everything is built from the primitives in
:mod:`mrcert.scenes.primitives`, coloured procedurally, and deterministic given its seed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mrcert.scenes.primitives import Surface, box, cylinder, rect, revolution, rotation, sphere, torus
from mrcert.scenes.textures import checks, finish, mottled, noise, patchwork_rug, rgb, roughcast, stripes

FLOOR_Z = -1.0
CEILING_Z = FLOOR_Z + 3.7
HALF = 3.0  # half the room's side
TABLE = 0.5  # table side
WALLS = ("north", "south", "east", "west")

Part = tuple[Surface, np.ndarray]

AMBIENT = 0.8
"""The room's share of ambient light (the rest is Lambert under ``textures.LIGHT``): a softly
lit room, in which a wall and the floor differ little in brightness. With 0.6 the walls behind
the object at the test pitch were much darker than the floor behind it at the training pitches,
and a small CNN read them as its large grey classes (laptop, washing machine); validation
accuracy after 8 epochs 0.925 with 0.8 against 0.67-0.78 with 0.6 (docs/method.md §3)."""


RUG = 2.0
"""Half the side of the patchwork rug under the table (m). The training views (pitch 25 deg and
more) see the floor behind the object, the test views (pitch 10 deg) a wall with its furniture:
on a plain floor a classifier learns that any colour behind the object is the object's (a brown
closet behind it read as the teddy bear); a floor of many colours teaches it otherwise
(docs/method.md §3)."""


ROOMS = ("furnished", "no_rug", "paper", "plain")
"""The room's versions (``room(style=...)``): ``furnished``, the room as built (a patchwork rug
under the table; door, window, blackboard, closets, clock, paintings and photographs on the
walls); ``no_rug``, furnished without the rug (generator 4's room); ``paper``, the paper's room:
no rug, the window in the walls' roughcast; ``plain``, bare walls, floor and ceiling of
roughcast plaster (docs/studies/resnet18_generalisation.md)."""


def _cloud(parts: list[Part], ambient: float = AMBIENT) -> tuple[np.ndarray, np.ndarray]:
    points = np.concatenate([s.points for s, _ in parts])
    colors = np.concatenate([finish(s, c, ambient) for s, c in parts])
    return points, colors


def _solid(surface: Surface, color) -> Part:
    return surface, rgb(color, len(surface.points))


def _wall_item(
    wall: str, along: float, z0: float, width: float, height: float, density: float, depth: float = 0.005
) -> Surface:
    """A flat rectangle on a wall, ``depth`` in front of it, centred at ``along`` on the wall."""
    frames = {  # origin at the wall's left end as seen from the room, u along, n inward
        "north": (np.array([-HALF, HALF - depth, 0.0]), np.array([1.0, 0, 0])),
        "south": (np.array([HALF, -HALF + depth, 0.0]), np.array([-1.0, 0, 0])),
        "east": (np.array([HALF - depth, HALF, 0.0]), np.array([0, -1.0, 0])),
        "west": (np.array([-HALF + depth, -HALF, 0.0]), np.array([0, 1.0, 0])),
    }
    origin, u = frames[wall]
    o = origin + u * (HALF + along - width / 2)
    o[2] = z0
    s = rect(o, [0, 0, height], u * width, density)  # uv: (height, along); normal z x u points out
    return Surface(s.points, -s.normals, s.uv)  # lit as a surface facing into the room


def _framed(
    wall, along, z0, width, height, density, frame_color, inner: Callable[[Surface], np.ndarray], border=0.04
) -> list[Part]:
    frame = _wall_item(wall, along, z0, width, height, density, depth=0.01)
    inner_s = _wall_item(wall, along, z0 + border, width - 2 * border, height - 2 * border, density, depth=0.015)
    return [_solid(frame, frame_color), (inner_s, inner(inner_s))]


def room(
    density: float, seed: int = 0, style: str = "furnished", ambient: float = AMBIENT
) -> tuple[np.ndarray, np.ndarray]:
    """Walls, floor, ceiling and, but in the ``plain`` style, the furniture on the walls (``ROOMS``),
    shaded with ``ambient`` light (1.0: unshaded, every surface its own colour)."""
    if style not in ROOMS:
        raise ValueError(f"unknown room style {style!r}; allowed: {', '.join(ROOMS)}")
    d = density
    parts: list[Part] = []
    floor = rect([-HALF, -HALF, FLOOR_Z], [2 * HALF, 0, 0], [0, 2 * HALF, 0], d)
    ceiling = rect([-HALF, -HALF, CEILING_Z], [0, 2 * HALF, 0], [2 * HALF, 0, 0], d)
    walls = [_wall_item(wall, 0.0, FLOOR_Z, 2 * HALF, CEILING_Z - FLOOR_Z, d, depth=0.0) for wall in WALLS]
    on_rug = (np.abs(floor.points[:, :2]) < (RUG if style == "furnished" else 0.0)).all(axis=1)
    parts.append((floor, np.where(on_rug[:, None], patchwork_rug(floor, RUG, seed), roughcast(floor, seed + 1))))
    parts += [(s, roughcast(s, seed + 2 + i)) for i, s in enumerate([ceiling, *walls])]
    if style == "plain":
        return _cloud(parts, ambient)

    # Door (north), window (east), blackboard (west), closets (south corners), clock (north).
    door = _wall_item("north", -1.6, FLOOR_Z, 0.9, 2.05, d, depth=0.01)
    parts.append((door, roughcast(door, seed + 7)))
    parts.append(_solid(_wall_item("north", -1.25, FLOOR_Z + 1.0, 0.1, 0.04, d, depth=0.03), (0.8, 0.75, 0.3)))
    window = _framed(
        "east",
        0.3,
        0.0,
        1.4,
        1.2,
        d,
        (0.95, 0.95, 0.95),
        lambda s: np.where(
            ((np.abs(s.uv[:, 0] - 0.56) < 0.025) | (np.abs(s.uv[:, 1] - 0.66) < 0.025))[:, None],
            [0.95, 0.95, 0.95],
            np.column_stack([0.55 + 0.25 * s.uv[:, 0] / 1.1, 0.75 + 0.1 * s.uv[:, 0], np.full(len(s.uv), 0.93)]),
        ),
        border=0.06,
    )
    if style == "paper":  # frame and pane in the walls' plaster, as the door
        window = [(w, roughcast(w, seed + 8 + i)) for i, (w, _) in enumerate(window)]
    parts += window
    rng = np.random.default_rng(seed)
    strokes = rng.uniform(0, 1, (6, 4))

    def chalk(s: Surface) -> np.ndarray:
        u, v = s.uv[:, 0], s.uv[:, 1]
        on = np.zeros(len(u), bool)
        for a, b, c, e in strokes:
            on |= np.abs(u - (0.15 + 0.6 * a) - 0.08 * np.sin(v * (6 + 10 * b) + 7 * c)) < 0.008 + 0.004 * e
        return np.where(on[:, None], [0.9, 0.92, 0.88], [0.12, 0.28, 0.18])

    parts += _framed("west", 0.2, 0.1, 2.0, 1.0, d, (0.55, 0.4, 0.25), chalk)
    for along in (-2.0, 2.0):  # two closets against the south wall
        c = np.array([-along, -HALF + 0.3, FLOOR_Z + 1.0])
        s = box(c, (1.0, 0.6, 2.0), d)
        split = np.abs(s.points[:, 0] - c[0]) < 0.006
        parts.append((s, np.where(split[:, None], [0.25, 0.16, 0.1], [0.62, 0.47, 0.32])))
        for dx in (-0.06, 0.06):
            parts.append(_solid(box(c + [dx, 0.31, 0.0], (0.03, 0.02, 0.12), d), (0.75, 0.72, 0.6)))
    # Wall clock above the door's right.
    face = revolution(np.array([[0.0, 0.0], [0.18, 0.0]]), d).moved(rotation("x", np.pi / 2), (0.2, HALF - 0.02, 1.6))
    ang = np.arctan2(face.points[:, 2] - 1.6, face.points[:, 0] - 0.2)
    rad = np.hypot(face.points[:, 2] - 1.6, face.points[:, 0] - 0.2)
    ticks = (rad > 0.14) & (np.abs(np.mod(ang, np.pi / 6) - np.pi / 12) > np.pi / 12 - 0.06)
    hands = ((np.abs(ang - 1.2) < 0.06) & (rad < 0.1)) | ((np.abs(ang + 0.4) < 0.05) & (rad < 0.14))
    rim = rad > 0.165
    dark = ticks | hands | rim
    parts.append((face, np.where(dark[:, None], [0.08, 0.08, 0.08], [0.96, 0.96, 0.94])))
    # Two paintings and two photographs.
    for i, (wall, along, z0, w, h) in enumerate(
        [
            ("south", 0.0, 0.3, 1.2, 0.8),
            ("east", -1.9, 0.4, 0.8, 1.0),
            ("west", -1.9, 0.6, 0.4, 0.3),
            ("north", 1.3, 0.5, 0.35, 0.45),
        ]
    ):
        blobs = rng.uniform(0, 1, (8, 6))

        def canvas(s: Surface, blobs=blobs, photo=i >= 2) -> np.ndarray:
            u, v = s.uv[:, 0] / max(s.uv[:, 0].max(), 1e-6), s.uv[:, 1] / max(s.uv[:, 1].max(), 1e-6)
            if photo:  # a landscape: sky, hills, ground
                hill = 0.45 + 0.1 * np.sin(v * 9 + blobs[0, 0] * 6)
                sky = np.column_stack([0.5 + 0.3 * u, 0.7 + 0.2 * u, np.full(len(u), 0.95)])
                return np.where((u < hill)[:, None], [0.25, 0.55, 0.2], sky)
            out = rgb((0.9, 0.88, 0.8), len(u))
            for x, y, r, cr, cg, cb in blobs:
                inside = (u - x) ** 2 + (v - y) ** 2 < (0.05 + 0.2 * r) ** 2
                out[inside] = (cr, cg, cb)
            return out

        parts += _framed(
            wall,
            along,
            z0,
            w,
            h,
            d,
            (0.3, 0.2, 0.1) if i < 2 else (0.1, 0.1, 0.1),
            canvas,
            border=0.05 if i < 2 else 0.02,
        )
    return _cloud(parts, ambient)


def table(density: float, ambient: float = AMBIENT) -> tuple[np.ndarray, np.ndarray]:
    """The 0.5 x 0.5 x 1 m table with its top surface at z = 0, shaded with ``ambient`` light."""
    top = box((0, 0, -0.015), (TABLE, TABLE, 0.03), density)
    legs = [
        box((sx * 0.21, sy * 0.21, (FLOOR_Z - 0.03) / 2), (0.04, 0.04, -FLOOR_Z - 0.03), density)
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    parts = [(s, roughcast(s, 7 + i)) for i, s in enumerate([top, *legs])]
    return _cloud(parts, ambient)


# --- the 20 object classes ----------------------------------------------------------------


def _apple(d):
    body = sphere(0.045, d, (0, 0, 0.041), squash=0.9)
    streak = 0.5 + 0.5 * noise(body.points, 0.04, 21)
    red = rgb((0.75, 0.08, 0.06), len(streak)) * (1 - streak[:, None] * 0.3) + streak[:, None] * [0.25, 0.2, 0.0]
    stem = cylinder(0.004, 0.02, d).moved(t=(0, 0, 0.075))
    leaf = sphere(0.012, d, (0.012, 0, 0.088), squash=0.3)
    return [(body, red), _solid(stem, (0.35, 0.22, 0.1)), _solid(leaf, (0.2, 0.5, 0.15))]


def _orange(d):
    body = sphere(0.047, d, (0, 0, 0.046))
    peel = mottled(body, (0.95, 0.52, 0.05), 0.08, 0.006, 22)
    return [(body, peel), _solid(sphere(0.006, d, (0, 0, 0.092)), (0.3, 0.45, 0.1))]


def _banana(d):
    arc = torus(0.12, 0.018, d, (np.pi / 2 - 0.9, np.pi / 2 + 0.9)).moved(t=(0, -0.09, 0.018))
    ang = np.arctan2(arc.points[:, 1] + 0.09, arc.points[:, 0])
    tip = np.abs(ang - np.pi / 2) > 0.8
    return [(arc, np.where(tip[:, None], [0.3, 0.22, 0.08], [0.95, 0.85, 0.2]))]


def _mug(d):
    wall = revolution(np.array([[0.0, 0.0], [0.042, 0.0], [0.042, 0.1], [0.038, 0.1], [0.038, 0.008], [0.0, 0.008]]), d)
    handle = torus(0.03, 0.008, d, (-np.pi / 2, np.pi / 2)).moved(rotation("x", np.pi / 2), (0.042, 0, 0.05))
    band = stripes(wall.points[:, 2], 0.1, (0.15, 0.3, 0.75), (0.95, 0.95, 0.95), duty=0.25)
    return [(wall, band), _solid(handle, (0.95, 0.95, 0.95))]


def _can(d):
    body = cylinder(0.033, 0.122, d)
    z = body.points[:, 2]
    color = np.where(((z < 0.01) | (z > 0.112))[:, None], [0.75, 0.75, 0.78], [0.8, 0.08, 0.1])
    label = np.abs(z - 0.06) < 0.015
    color[label] = (0.95, 0.95, 0.95)
    return [(body, color)]


def _bottle(d):
    s = revolution(
        np.array([[0, 0], [0.035, 0], [0.035, 0.15], [0.014, 0.2], [0.013, 0.25], [0.015, 0.25], [0.0, 0.25]]), d
    )
    z = s.points[:, 2]
    color = np.where((np.abs(z - 0.08) < 0.03)[:, None], [0.9, 0.85, 0.6], [0.15, 0.45, 0.2])
    color[z > 0.235] = (0.7, 0.65, 0.1)
    return [(s, color)]


def _vase(d):
    s = revolution(
        np.array([[0, 0], [0.032, 0], [0.058, 0.09], [0.05, 0.15], [0.022, 0.2], [0.032, 0.24], [0.0, 0.24]]), d
    )
    pattern = stripes(s.uv[:, 0], 0.03, (0.15, 0.25, 0.65), (0.85, 0.88, 0.95), duty=0.35)
    return [(s, pattern)]


def _bowl(d):
    s = revolution(np.array([[0.0, 0.0], [0.04, 0.0], [0.09, 0.06], [0.085, 0.062], [0.036, 0.008], [0.0, 0.008]]), d)
    rim = s.points[:, 2] > 0.05
    return [(s, np.where(rim[:, None], [0.7, 0.2, 0.15], [0.93, 0.9, 0.8]))]


def _potted_plant(d):
    pot = revolution(np.array([[0, 0], [0.05, 0], [0.065, 0.1], [0.0, 0.1]]), d)
    leaves = [
        sphere(0.045, d, (0.035 * np.cos(a), 0.035 * np.sin(a), 0.15 + 0.03 * (k % 2)), squash=0.7)
        for k, a in enumerate(np.linspace(0, 2 * np.pi, 5, endpoint=False))
    ]
    top = sphere(0.05, d, (0, 0, 0.21))
    foliage = Surface.concat([*leaves, top])
    return [_solid(pot, (0.72, 0.36, 0.2)), (foliage, mottled(foliage, (0.2, 0.55, 0.18), 0.25, 0.02, 23))]


def _lamp(d):
    base = cylinder(0.06, 0.02, d)
    pole = cylinder(0.007, 0.22, d).moved(t=(0, 0, 0.02))
    shade = revolution(np.array([[0.09, 0.2], [0.05, 0.3]]), d)
    return [_solid(base, (0.15, 0.15, 0.15)), _solid(pole, (0.7, 0.7, 0.7)), _solid(shade, (0.98, 0.88, 0.55))]


def _book(d):
    s = box((0, 0, 0.02), (0.15, 0.21, 0.04), d)
    pages = (np.abs(s.normals[:, 2]) < 0.5) & (s.points[:, 0] > -0.07)
    color = np.where(
        pages[:, None], stripes(s.points[:, 2], 0.004, (0.95, 0.93, 0.85), (0.8, 0.78, 0.7)), [0.55, 0.1, 0.12]
    )
    title = (np.abs(s.points[:, 1] - 0.05) < 0.015) & (s.normals[:, 2] > 0.5)
    color[title] = (0.85, 0.75, 0.3)
    return [(s, color)]


def _laptop(d):
    base = box((0, 0, 0.008), (0.3, 0.2, 0.016), d)
    keys = (base.normals[:, 2] > 0.5) & (np.abs(base.points[:, 1] + 0.01) < 0.06)
    bc = np.where(
        keys[:, None],
        checks(base.points[:, 0], base.points[:, 1], 0.012, (0.2, 0.2, 0.2), (0.35, 0.35, 0.35)),
        [0.75, 0.75, 0.78],
    )
    screen = box((0, 0.0, 0.1), (0.3, 0.008, 0.2), d).moved(rotation("x", -0.35), (0, 0.11, 0.0))
    front = screen.normals[:, 1] < -0.5
    sc = np.where(front[:, None], [0.1, 0.2, 0.45], [0.75, 0.75, 0.78])
    return [(base, bc), (screen, sc)]


def _keyboard(d):
    s = box((0, 0, 0.01), (0.36, 0.13, 0.02), d)
    top = s.normals[:, 2] > 0.5
    keys = checks(s.points[:, 0] + 0.004, s.points[:, 1], 0.018, (0.85, 0.85, 0.85), (0.2, 0.2, 0.22))
    return [(s, np.where(top[:, None], keys, [0.2, 0.2, 0.22]))]


def _mouse(d):
    s = sphere(0.03, d, (0, 0, 0.0), squash=0.6)
    s = Surface(s.points * [1.0, 0.6, 1.0] + [0, 0, 0.018], s.normals, s.uv)
    wheel = (np.abs(s.points[:, 1]) < 0.003) & (s.points[:, 0] > 0.005)
    return [(s, np.where(wheel[:, None], [0.05, 0.05, 0.05], [0.6, 0.6, 0.62]))]


def _telephone(d):
    base = box((0, 0, 0.03), (0.18, 0.15, 0.06), d)
    pad = (base.normals[:, 2] > 0.5) & (base.points[:, 1] < 0.0)
    bc = np.where(
        pad[:, None],
        checks(base.points[:, 0], base.points[:, 1], 0.015, (0.85, 0.85, 0.8), (0.1, 0.1, 0.1)),
        [0.1, 0.1, 0.1],
    )
    handset = Surface.concat(
        [
            box((0, 0.045, 0.075), (0.16, 0.045, 0.03), d),
            sphere(0.025, d, (-0.08, 0.045, 0.08)),
            sphere(0.025, d, (0.08, 0.045, 0.08)),
        ]
    )
    return [(base, bc), _solid(handset, (0.12, 0.12, 0.12))]


def _clock(d):
    disk = cylinder(0.08, 0.03, d).moved(rotation("x", np.pi / 2), (0, 0.015, 0.09))
    rel = disk.points - [0, 0, 0.09]
    ang, rad = np.arctan2(rel[:, 2], rel[:, 0]), np.hypot(rel[:, 2], rel[:, 0])
    front = np.abs(disk.normals[:, 1]) > 0.5
    ticks = (rad > 0.06) & (np.abs(np.mod(ang, np.pi / 6) - np.pi / 12) > np.pi / 12 - 0.1)
    hands = ((np.abs(ang - 1.0) < 0.08) & (rad < 0.05)) | ((np.abs(ang + 2.2) < 0.07) & (rad < 0.068))
    color = np.where(
        front[:, None], np.where((ticks | hands)[:, None], [0.05, 0.05, 0.05], [0.97, 0.95, 0.85]), [0.65, 0.5, 0.15]
    )
    feet = Surface.concat([box((dx, 0, 0.006), (0.03, 0.04, 0.012), d) for dx in (-0.04, 0.04)])
    return [(disk, color), _solid(feet, (0.3, 0.25, 0.1))]


def _teddy_bear(d):
    fur = Surface.concat(
        [
            sphere(0.06, d, (0, 0, 0.07), squash=1.1),
            sphere(0.045, d, (0, 0, 0.17)),
            sphere(0.018, d, (0.035, 0, 0.205)),
            sphere(0.018, d, (-0.035, 0, 0.205)),
            sphere(0.025, d, (0.06, -0.02, 0.1)),
            sphere(0.025, d, (-0.06, -0.02, 0.1)),
            sphere(0.027, d, (0.035, -0.04, 0.025)),
            sphere(0.027, d, (-0.035, -0.04, 0.025)),
        ]
    )
    face = Surface.concat([sphere(0.02, d, (0, -0.04, 0.16))])
    eyes = Surface.concat([sphere(0.006, d, (dx, -0.04, 0.185)) for dx in (-0.015, 0.015)])
    return [
        (fur, mottled(fur, (0.55, 0.35, 0.18), 0.15, 0.01, 24)),
        _solid(face, (0.85, 0.7, 0.5)),
        _solid(eyes, (0.05, 0.05, 0.05)),
    ]


def _toy_car(d):
    body = box((0, 0, 0.04), (0.2, 0.09, 0.045), d)
    cabin = box((-0.01, 0, 0.08), (0.1, 0.08, 0.04), d)
    glass = np.abs(cabin.normals[:, 2]) < 0.5
    wheels = Surface.concat(
        [
            cylinder(0.02, 0.015, d).moved(rotation("x", np.pi / 2), (x, y, 0.02))
            for x in (-0.06, 0.06)
            for y in (0.06, -0.045)
        ]
    )
    return [
        _solid(body, (0.85, 0.1, 0.1)),
        (cabin, np.where(glass[:, None], [0.5, 0.7, 0.9], [0.85, 0.1, 0.1])),
        _solid(wheels, (0.08, 0.08, 0.08)),
    ]


def _kettle(d):
    body = revolution(np.array([[0, 0], [0.08, 0], [0.085, 0.06], [0.07, 0.14], [0.035, 0.16], [0.0, 0.16]]), d)
    spout = cylinder(0.012, 0.09, d, caps=False).moved(rotation("y", 0.9), (0.07, 0, 0.06))
    handle = torus(0.055, 0.01, d, (0.0, np.pi)).moved(rotation("x", np.pi / 2), (0, 0, 0.15))
    knob = sphere(0.012, d, (0, 0, 0.168))
    metal = mottled(body, (0.78, 0.8, 0.82), 0.05, 0.03, 25)
    return [
        (body, metal),
        _solid(spout, (0.78, 0.8, 0.82)),
        _solid(handle, (0.1, 0.1, 0.1)),
        _solid(knob, (0.1, 0.1, 0.1)),
    ]


def _washing_machine(d):
    s = box((0, 0, 0.15), (0.25, 0.25, 0.3), d)
    front = s.normals[:, 1] < -0.5
    rel = s.points[:, [0, 2]] - [0, 0.13]
    r = np.hypot(rel[:, 0], rel[:, 1])
    color = rgb((0.95, 0.95, 0.95), len(r))
    color[front & (r < 0.08)] = (0.25, 0.3, 0.4)
    color[front & (r >= 0.08) & (r < 0.095)] = (0.6, 0.6, 0.62)
    color[front & (s.points[:, 2] > 0.26)] = (0.8, 0.82, 0.85)
    color[front & (s.points[:, 2] > 0.27) & (np.abs(s.points[:, 0] - 0.08) < 0.012)] = (0.2, 0.2, 0.2)
    return [(s, color)]


OBJECTS: dict[str, Callable[[float], list[Part]]] = {
    "apple": _apple,
    "banana": _banana,
    "book": _book,
    "bottle": _bottle,
    "bowl": _bowl,
    "can": _can,
    "clock": _clock,
    "computer_mouse": _mouse,
    "keyboard": _keyboard,
    "kettle": _kettle,
    "lamp": _lamp,
    "laptop": _laptop,
    "mug": _mug,
    "orange": _orange,
    "potted_plant": _potted_plant,
    "telephone": _telephone,
    "teddy_bear": _teddy_bear,
    "toy_car": _toy_car,
    "vase": _vase,
    "washing_machine": _washing_machine,
}
CLASSES: tuple[str, ...] = tuple(sorted(OBJECTS))
"""Class names; labels are their alphabetical order, as in the released MetaRoom."""


OBJECT_SCALE = 2.0
"""The objects are modelled at twice their everyday size (largest extents 0.12 to 0.72 m).
At life size the smallest cover a few pixels at the test distance (a 6 cm mouse: 8 px), and
classifiers trained on the training pitches did not generalise to a pitch 15 degrees below
them: on a development protocol (training pitches 40-90, held-out rings at pitch 25, no test
view involved) a small CNN reached 0.47 at life size, 0.83 at twice it, 0.80 at three times
(tall objects leave the frame) and 0.48 with every object scaled to the same 0.3 m (size is a
cue)."""


def object_cloud(name: str, density: float, ambient: float = AMBIENT) -> tuple[np.ndarray, np.ndarray]:
    """The object standing on the table top (z = 0), centred on the z axis, ``OBJECT_SCALE``
    times its modelled size, its surface sampled ``density`` apart and shaded with ``ambient`` light."""
    if name not in OBJECTS:
        raise ValueError(f"unknown MetaRoom class {name!r}; allowed: {', '.join(CLASSES)}")
    points, colors = _cloud(OBJECTS[name](density / OBJECT_SCALE), ambient)
    return points * OBJECT_SCALE, colors
