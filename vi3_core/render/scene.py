"""Textured box worlds: a room (floor, ceiling, four walls) with axis-aligned boxes standing on the floor.

World W is z-up (as in ``vi3_core.sim``). Every surface is an axis-aligned rectangle with its own procedural
texture; all textures live in one flat atlas so that the ray caster looks them up with a single gather.
Face ids: room faces ``2*axis + side`` (side 0 = low wall, 1 = high wall), box ``b`` faces
``6 + 6*b + 2*axis + side``. Each scene also names the free flight volume (``center`` +- ``extent``) that the
trajectories stay in: boxes keep ``clearance`` metres away from it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vi3_core.render.textures import procedural_texture


@dataclass(frozen=True)
class SceneSpec:
    """Room bounds [3] (m), flight volume, box count and size range, texel size (m); the room's and the boxes' surfaces:
    mean grey (0-1), contrast (the texture's standard deviation), rectangles per square metre (posters, sockets,
    handles: what corners a plain surface has) and their own contrast (None: part of the texture); ``box_tones``: the
    spread each box's mean grey is drawn in around the boxes' (furniture of many colours)."""

    room_lo: tuple[float, float, float]
    room_hi: tuple[float, float, float]
    center: tuple[float, float, float]
    extent: tuple[float, float, float]
    n_boxes: int
    box_size: tuple[float, float]
    box_height: tuple[float, float]
    texel: float = 0.005
    clearance: float = 0.6
    wall: tuple[float, float, float, float | None] = (0.5, 0.17, 40.0, None)
    box: tuple[float, float, float, float | None] = (0.5, 0.17, 40.0, None)
    box_tones: float = 0.0


SCENES: dict[str, SceneSpec] = {
    "room": SceneSpec((-4.0, -3.5, 0.0), (4.0, 3.5, 3.0), (0.0, 0.0, 1.4), (1.6, 1.4, 0.4),
                      n_boxes=7, box_size=(0.4, 1.2), box_height=(0.4, 1.6)),
    "hall": SceneSpec((-6.0, -4.5, 0.0), (6.0, 4.5, 4.5), (0.0, 0.0, 1.8), (2.8, 2.0, 0.6),
                      n_boxes=12, box_size=(0.5, 1.5), box_height=(0.6, 2.5), texel=0.008),
    "corridor": SceneSpec((-6.0, -1.6, 0.0), (6.0, 1.6, 2.8), (0.0, 0.0, 1.3), (3.5, 0.3, 0.3),
                          n_boxes=8, box_size=(0.3, 0.7), box_height=(0.3, 1.2), clearance=0.4),
    # a bedroom as a handheld RealSense recording shows one: light walls of little texture with what hangs on them
    # (a rectangle every few square metres), dark furniture with its clutter; sized so that the front end finds as
    # many corners per frame in it as in the recording (docs/accuracy.md: 415 live tracks against 381)
    "bedroom": SceneSpec((-2.2, -1.9, 0.0), (2.2, 1.9, 2.6), (0.0, 0.0, 1.3), (0.8, 0.6, 0.25),
                         n_boxes=12, box_size=(0.3, 1.4), box_height=(0.3, 1.9), clearance=0.3,
                         wall=(0.62, 0.10, 8.0, 0.5), box=(0.3, 0.20, 30.0, 0.3), box_tones=0.2),
}

#: In-plane (u, v) axes of a face whose normal is along axis a.
_UV = np.array([[1, 2], [0, 2], [0, 1]])
_LIGHT = np.array([0.35, -0.5, 0.79])


@dataclass(frozen=True)
class Scene:
    """A box world ready for ray casting.

    room_lo, room_hi: [3]; box_lo, box_hi: [B,3] (m, W). Per face f (F = 6 + 6B): ``face_axis`` normal axis,
    ``face_origin`` [F,2] world (u, v) of texel (0, 0), ``tex_offset``/``tex_w``/``tex_h`` position in the atlas,
    ``shade`` Lambertian factor of a fixed distant light. ``atlas``: all textures, flattened, uint8 grey levels
    (one byte per texel keeps the random lookups cache-friendly).
    """

    name: str
    seed: int
    room_lo: np.ndarray
    room_hi: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    center: np.ndarray
    extent: np.ndarray
    texel: float
    face_axis: np.ndarray
    face_origin: np.ndarray
    tex_offset: np.ndarray
    tex_w: np.ndarray
    tex_h: np.ndarray
    shade: np.ndarray
    atlas: np.ndarray


def _place_boxes(rng: np.random.Generator, spec: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    """Boxes on the floor, inside the room, clear of the flight volume and (mostly) of each other."""
    lo, hi = np.asarray(spec.room_lo), np.asarray(spec.room_hi)
    keep_lo = np.asarray(spec.center) - spec.extent - spec.clearance
    keep_hi = np.asarray(spec.center) + spec.extent + spec.clearance
    cand = 400
    size = rng.uniform(*spec.box_size, size=(cand, 2))
    height = rng.uniform(*spec.box_height, size=cand)
    xy = rng.uniform(lo[:2] + size / 2 + 0.05, hi[:2] - size / 2 - 0.05)
    b_lo = np.concatenate([xy - size / 2, np.full((cand, 1), lo[2])], 1)
    b_hi = np.concatenate([xy + size / 2, (lo[2] + height)[:, None]], 1)
    clear = np.any((b_hi < keep_lo) | (b_lo > keep_hi), axis=1)
    b_lo, b_hi = b_lo[clear], b_hi[clear]
    # Greedy non-overlap, in candidate order (deterministic): small loop over <= n_boxes accepted boxes.
    chosen: list[int] = []
    for i in range(len(b_lo)):
        if len(chosen) == spec.n_boxes:
            break
        if all(np.any((b_hi[i, :2] < b_lo[j, :2]) | (b_lo[i, :2] > b_hi[j, :2])) for j in chosen):
            chosen.append(i)
    return b_lo[chosen], b_hi[chosen]


def _around(spec: SceneSpec, center: np.ndarray, extent: np.ndarray) -> SceneSpec:
    """``spec`` moved and grown to hold the flight volume ``center`` +- ``extent`` [3] (m, W): floor, ceiling and
    walls keep the spec's distances from the flight volume; the box count grows with the floor area."""
    lo = np.asarray(spec.center) - spec.extent - spec.room_lo
    hi = np.asarray(spec.room_hi) - spec.center - spec.extent
    room_lo, room_hi = center - extent - lo, center + extent + hi
    area = np.prod((room_hi - room_lo)[:2]) / np.prod((np.asarray(spec.room_hi) - spec.room_lo)[:2])
    return replace(spec, room_lo=tuple(room_lo), room_hi=tuple(room_hi), center=tuple(center), extent=tuple(extent),
                   n_boxes=int(round(spec.n_boxes * max(area, 1.0))))


def make_scene(name: str = "room", seed: int = 0, *, center=None, extent=None) -> Scene:
    """The scene ``name`` (one of ``SCENES``) with boxes and textures drawn from ``seed``.

    ``center`` and ``extent`` [3] (m, W): a flight volume to hold instead of the scene's own, e.g. the bounding box
    of a recorded trajectory (the room is moved and grown around it, see ``_around``).
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {sorted(SCENES)}")
    spec = SCENES[name]
    if center is not None or extent is not None:
        if center is None or extent is None:
            raise ValueError("make_scene needs both center and extent, or neither")
        spec = _around(spec, np.asarray(center, dtype=np.float64), np.asarray(extent, dtype=np.float64))
    rng = np.random.default_rng([seed, 7151])
    room_lo, room_hi = np.asarray(spec.room_lo, float), np.asarray(spec.room_hi, float)
    box_lo, box_hi = _place_boxes(rng, spec)
    los = np.concatenate([room_lo[None], box_lo])
    his = np.concatenate([room_hi[None], box_hi])
    axis = np.tile(np.repeat(np.arange(3), 2), len(los))
    side = np.tile([0, 1], 3 * len(los))
    owner = np.repeat(np.arange(len(los)), 6)
    uv = _UV[axis]
    origin = np.take_along_axis(los[owner], uv, 1)
    size = np.take_along_axis(his[owner], uv, 1) - origin
    tex_w = np.ceil(size[:, 0] / spec.texel).astype(np.int64) + 2
    tex_h = np.ceil(size[:, 1] / spec.texel).astype(np.int64) + 2
    tone = np.zeros(len(los))
    if spec.box_tones:
        tone[1:] = rng.uniform(-spec.box_tones, spec.box_tones, len(los) - 1)
    surface = [spec.wall if o == 0 else (spec.box[0] + tone[o], *spec.box[1:]) for o in owner]
    textures = [procedural_texture(rng, (int(h), int(w)), texel=spec.texel, mean=m, contrast=c, rect_density=r,
                                   rect_contrast=rc).reshape(-1)
                for h, w, (m, c, r, rc) in zip(tex_h, tex_w, surface)]
    offset = np.concatenate([[0], np.cumsum([len(t) for t in textures])[:-1]]).astype(np.int64)
    # Outward normal of each face as seen by the camera: room faces face inwards, box faces outwards.
    normal = np.zeros((len(axis), 3))
    inward = np.where(owner == 0, 1.0, -1.0)
    normal[np.arange(len(axis)), axis] = np.where(side == 0, 1.0, -1.0) * inward
    shade = (0.65 + 0.3 * (normal @ (_LIGHT / np.linalg.norm(_LIGHT)))).astype(np.float32)
    return Scene(name=name, seed=seed, room_lo=room_lo, room_hi=room_hi, box_lo=box_lo, box_hi=box_hi,
                 center=np.asarray(spec.center, float), extent=np.asarray(spec.extent, float), texel=spec.texel,
                 face_axis=axis, face_origin=origin.astype(np.float32), tex_offset=offset, tex_w=tex_w,
                 tex_h=tex_h, shade=shade, atlas=np.rint(np.concatenate(textures) * 255).astype(np.uint8))
