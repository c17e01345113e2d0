"""The packed particle meshes of one scene (``geometry.npz``), shared by all stages, and the
length unit they are handed to pybullet in.

Only numpy here: the simulate, render and label stages import this without the cost of scipy.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from .. import PsdError

# pybullet's length unit here, for the physics and the TinyRenderer alike: centimetres (millimetres
# and metres were measured to misbehave in Bullet). Everything outside pybullet is in mm.
CM = 0.1  # mm → cm


@dataclass
class Geometry:
    """The packed meshes of one scene."""

    vertices: np.ndarray
    faces: np.ndarray
    vert_offsets: np.ndarray
    face_offsets: np.ndarray
    size_mm: np.ndarray  # the drawn size: the b-axis
    volume_mm3: np.ndarray
    dims_mm: np.ndarray  # minimum-volume bounding box sides, a ≥ b ≥ c
    sieve_mm: np.ndarray  # the side of the smallest square hole each particle passes

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Geometry:
        try:
            return cls(**{k: arrays[k] for k in cls.__dataclass_fields__})
        except KeyError as e:
            raise PsdError(f"geometry file lacks the array {e}; rerun the sample job") from None

    def __len__(self) -> int:
        return len(self.size_mm)

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        v = self.vertices[self.vert_offsets[i] : self.vert_offsets[i + 1]].astype(np.float64)
        f = self.faces[self.face_offsets[i] : self.face_offsets[i + 1]]
        return v, f


def global_faces(geometry: Geometry) -> np.ndarray:
    """Every face (F, 3) as indices into ``geometry.vertices`` (its vertices' ids are per particle)."""
    return geometry.faces + np.repeat(geometry.vert_offsets[:-1], np.diff(geometry.face_offsets))[:, None]


def mesh_normals(v: np.ndarray, f: np.ndarray, smooth: bool) -> np.ndarray:
    """Unit normals of the triangles `f` (F, 3) over vertices `v` (V, 3): each face's (F, 3), or with
    `smooth` each vertex's (V, 3), the area-weighted mean of its faces' (shaded smooth)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if smooth:
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], n)
        n = vn
    return n / (np.linalg.norm(n, axis=1, keepdims=True) + 1e-12)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions x, y, z, w (pybullet's order) → (N, 3, 3) rotation matrices."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


@contextmanager
def gc_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off for the block: handing pybullet a scene's meshes makes
    ~10^5 small lists, and each collection they trigger walks all of them (measured: a fifth of a
    render, none of it needed: no cycles are made)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()
