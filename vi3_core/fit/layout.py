"""The one named layout of the unknowns of a metric fit, and of the vector its Gaussian priors are written on.

Every column of the fit's Jacobian and every entry of its parameter change dx has a slot here; solver, priors,
marginalisation and the online window's restart address them by name, never by a literal index. A new unknown is a
new entry of ``SHARED`` or ``PER_CLIP`` (or of ``PRIOR``), and every user follows.

Parameter change dx (``StateLayout``), in this order:
    shared:   g (2: gravity's tangent plane, its norm is fixed), ba (3, m/s^2, IMU frame), bg (3, rad/s, IMU frame),
              td (1, s: the camera-IMU time offset left over after the configured one)
    per clip: lam (1: 1 / scale), v (3: first-frame velocity in B0, m/s), c (3: offset of the clip's first frame,
              model units)
Prior vector z (``PriorLayout``): g (3, m/s^2, B0), ba (3), bg (3), v (3, m/s, B0), lam (1): the velocity and 1 / scale
of the clip the prior is written at (its scale is what a link to the clips before carries forward), td (1, s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SHARED: tuple[tuple[str, int], ...] = (("g", 2), ("ba", 3), ("bg", 3), ("td", 1))
PER_CLIP: tuple[tuple[str, int], ...] = (("lam", 1), ("v", 3), ("c", 3), ("dphi", 3))
PRIOR: tuple[tuple[str, int], ...] = (("g", 3), ("ba", 3), ("bg", 3), ("v", 3), ("lam", 1), ("td", 1))


def _offsets(blocks: tuple[tuple[str, int], ...]) -> tuple[dict[str, slice], int]:
    out, o = {}, 0
    for name, size in blocks:
        out[name] = slice(o, o + size)
        o += size
    return out, o


_SHARED, N_SHARED = _offsets(SHARED)
_CLIP, N_CLIP = _offsets(PER_CLIP)
_PRIOR, N_PRIOR = _offsets(PRIOR)


@dataclass(frozen=True)
class StateLayout:
    """The columns of a fit of K clips: the shared unknowns, then one ``PER_CLIP`` block per clip.

    ``layout.g`` / ``.ba`` / ``.bg``: slices of the shared unknowns; ``layout.lam(k)`` (an int), ``.v(k)``, ``.c(k)``:
    clip k's; ``layout.clip(k)``: clip k's whole block; ``lams`` [K], ``vs`` [K,3], ``cs`` [K,3]: index arrays of every
    clip's (``dx[layout.vs]`` is [K,3]). ``StateLayout(1)`` is also the column order of one clip's own Jacobian
    block beside the shared columns."""

    K: int

    @property
    def n(self) -> int:
        """The number of unknowns."""
        return N_SHARED + N_CLIP * self.K

    @property
    def shared(self) -> slice:
        return slice(0, N_SHARED)

    @property
    def g(self) -> slice:
        return _SHARED["g"]

    @property
    def ba(self) -> slice:
        return _SHARED["ba"]

    @property
    def bg(self) -> slice:
        return _SHARED["bg"]

    @property
    def td(self) -> int:
        return _SHARED["td"].start

    @staticmethod
    def in_clip(name: str) -> slice:
        """Where ``name`` ("lam", "v", "c") sits inside a clip's block."""
        return _CLIP[name]

    def clip(self, k: int) -> slice:
        o = N_SHARED + N_CLIP * k
        return slice(o, o + N_CLIP)

    def _in_clip(self, name: str, k: int) -> slice:
        o, part = N_SHARED + N_CLIP * k, _CLIP[name]
        return slice(o + part.start, o + part.stop)

    def lam(self, k: int) -> int:
        return self._in_clip("lam", k).start

    def v(self, k: int) -> slice:
        return self._in_clip("v", k)

    def c(self, k: int) -> slice:
        return self._in_clip("c", k)

    def dphi(self, k: int) -> slice:
        return self._in_clip("dphi", k)

    def _every(self, name: str) -> np.ndarray:
        part = _CLIP[name]
        return N_SHARED + N_CLIP * np.arange(self.K)[:, None] + np.arange(part.start, part.stop)[None, :]

    @property
    def lams(self) -> np.ndarray:
        return self._every("lam")[:, 0]

    @property
    def vs(self) -> np.ndarray:
        return self._every("v")

    @property
    def cs(self) -> np.ndarray:
        return self._every("c")

    @property
    def dphis(self) -> np.ndarray:
        return self._every("dphi")

    def prior_columns(self, k: int) -> np.ndarray:
        """The columns a prior written at clip k speaks about, in ``PriorLayout`` order (g's tangent for its 3)."""
        return np.r_[self.g, self.ba, self.bg, self.v(k), self.lam(k), self.td]

    def prior_jacobian(self, k: int, GB: np.ndarray) -> np.ndarray:
        """[N_PRIOR, n]: d z / d dx for the prior vector z at clip k; GB [3,2] = |g| times g's tangent basis."""
        Jz = np.zeros((N_PRIOR, self.n))
        Jz[PriorLayout.g, self.g] = GB
        Jz[PriorLayout.ba, self.ba] = np.eye(3)
        Jz[PriorLayout.bg, self.bg] = np.eye(3)
        Jz[PriorLayout.v, self.v(k)] = np.eye(3)
        Jz[PriorLayout.lam, self.lam(k)] = 1.0
        Jz[PriorLayout.td, self.td] = 1.0
        return Jz


class PriorLayout:
    """Slices of the prior vector z (``PRIOR``): ``g``, ``ba``, ``bg``, ``v``, ``lam``, ``td``; ``n`` entries."""

    g = _PRIOR["g"]
    ba = _PRIOR["ba"]
    bg = _PRIOR["bg"]
    v = _PRIOR["v"]
    lam = _PRIOR["lam"]
    td = _PRIOR["td"]
    n = N_PRIOR

    @staticmethod
    def vector(g: np.ndarray, ba: np.ndarray, bg: np.ndarray, v: np.ndarray, lam: float, td: float) -> np.ndarray:
        """z [n] from its parts."""
        z = np.empty(N_PRIOR)
        Z = PriorLayout
        z[Z.g], z[Z.ba], z[Z.bg], z[Z.v], z[Z.lam], z[Z.td] = g, ba, bg, v, lam, td
        return z


__all__ = ["N_CLIP", "N_PRIOR", "N_SHARED", "PriorLayout", "StateLayout"]
