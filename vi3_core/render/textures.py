"""Procedural grey-level textures with detail at every scale a 752x480 camera sees in a room.

Each texture is a sum of band-limited value-noise octaves (1 m down to 2 cm) plus scattered rectangles
("posters", "tiles", "crates") whose corners give corner detectors something to lock on to. Everything is
drawn from one ``numpy.random.Generator``, so a seed reproduces the texture bit for bit.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Octave wavelengths in metres and their relative amplitudes.
_OCTAVES = ((1.0, 0.35), (0.3, 0.3), (0.1, 0.3), (0.04, 0.25), (0.02, 0.2))


def _noise_octave(rng: np.random.Generator, h: int, w: int, cells: float) -> np.ndarray:
    """Bicubically upsampled white noise with ``cells`` texels per noise cell: [h,w] float32, ~unit std."""
    gh, gw = int(np.ceil(h / cells)) + 3, int(np.ceil(w / cells)) + 3
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(round(gw * cells)), int(round(gh * cells))), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def _rectangles(rng: np.random.Generator, h: int, w: int, texel: float, density: float) -> np.ndarray:
    """Flat rectangles of random grey offsets (3-40 cm), about ``density`` per square metre: [h,w] float32."""
    layer = np.zeros((h, w), np.float32)
    count = int(rng.poisson(density * h * w * texel**2))
    size = rng.uniform(0.03, 0.4, size=(count, 2)) / texel
    x0 = rng.uniform(-size[:, 0], w)
    y0 = rng.uniform(-size[:, 1], h)
    value = rng.uniform(-0.5, 0.5, size=count)
    corners = np.stack([x0, y0, x0 + size[:, 0], y0 + size[:, 1]], 1).round().astype(np.int32)
    for (a, b, c, d), v in zip(corners.tolist(), value.tolist()):  # one draw call per rectangle (setup only)
        cv2.rectangle(layer, (a, b), (c, d), v, thickness=-1)
    return layer


def procedural_texture(rng: np.random.Generator, shape: tuple[int, int], *, texel: float,
                       rect_density: float = 40.0, mean: float = 0.5, contrast: float = 0.17,
                       rect_contrast: float | None = None) -> np.ndarray:
    """A texture of ``shape`` (h, w) texels of ``texel`` metres: float32 in [0.04, 0.96], about ``mean`` with a
    standard deviation of ``contrast``; ``rect_contrast``: the rectangles' own grey offsets (times [-0.5, 0.5]) on a
    plain surface (painted walls: a switch, a picture), else they are part of the texture its contrast is set for."""
    h, w = shape
    tex = np.zeros((h, w), np.float32)
    for wavelength, amp in _OCTAVES:
        tex += amp * _noise_octave(rng, h, w, max(wavelength / texel, 1.0))
    rects = _rectangles(rng, h, w, texel, rect_density)
    if rect_contrast is None:
        tex += 1.6 * rects
    # Band-limit to about two texels so that bilinear lookups do not alias at EuRoC's pixel footprint.
    tex = cv2.GaussianBlur(tex, (0, 0), 0.8)
    tex = mean + contrast * (tex - tex.mean()) / max(float(tex.std()), 1e-6)
    if rect_contrast is not None:
        tex += 2.0 * rect_contrast * cv2.GaussianBlur(rects, (0, 0), 0.8)
    return np.clip(tex, 0.04, 0.96)
