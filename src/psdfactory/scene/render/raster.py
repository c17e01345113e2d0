"""The ``tiny`` backend's rasteriser, compiled: pybullet's TinyRenderer, pixel for pixel, ~10× faster.

TinyRenderer (``getCameraImage(renderer=ER_TINY_RENDERER)``) rasterises every triangle of every
particle on the CPU, and each particle's mesh is first handed to it as Python lists; at the paper's
scene size (1,000 particles, 1024² at supersample 2) that was 0.45 s of the render's 0.75 s. This
module draws the same triangles with the same rules, compiled by numba:

- the camera's matrices are pybullet's own (``computeViewMatrix``, ``computeProjectionMatrixFOV``),
  and TinyRenderer's viewport;
- a pixel (x, y) is sampled at its integer coordinates, inside a triangle when all three of its
  barycentric coordinates are ≥ 0 (TinyRenderer's test, degenerate triangles skipped alike), and the
  nearest surface wins (at a tie the later triangle, as there);
- normals are interpolated perspective-correctly and shaded as TinyRenderer's shader does:
  each channel min(255, floor(floor(255·colour) · (ambient + (kd·max(0, n·l) + ks·max(0, r_z)²) ·
  light colour))), r the light reflected about n: the ambient light white, the key light coloured
  (the exponent and the order of the truncations found by fitting TinyRenderer's output; on the
  test scenes every colour byte is TinyRenderer's).

Measured against TinyRenderer (``tests/test_render.py``, and on paper scenes): the segmentation is
identical, the heights agree to float rounding (~0.004 mm), and the colours are its bytes, bar a rare
pixel a level off where a normal sits on a truncation step (TinyRenderer computes in float32).
``PSDFACTORY_RASTERISER=pybullet`` renders with TinyRenderer itself (where numba cannot be imported,
that is the fallback).
"""

from __future__ import annotations

import logging
import math
import os

import numpy as np

from ... import PsdError
from ..geometry import CM, Geometry, global_faces, mesh_normals, quat_to_matrix

logger = logging.getLogger(__name__)

RASTERISERS = ("numba", "pybullet")
ENV = "PSDFACTORY_RASTERISER"
SPECULAR_EXPONENT = 2.0  # TinyRenderer's, for a model without a specular map (found by fitting its output)
SPECULAR_COEFF = 0.05  # the key light's specular coefficient (tiny.py gives TinyRenderer the same)

_kernel = None


def rasteriser() -> str:
    """Which rasteriser the ``tiny`` backend uses: $PSDFACTORY_RASTERISER, else numba where it imports."""
    want = os.environ.get(ENV, "").strip().lower() or "numba"
    if want not in RASTERISERS:
        raise PsdError(f"{ENV}={want!r} is no rasteriser: set it to one of {', '.join(RASTERISERS)}, or unset it")
    if want == "numba" and _compiled() is None:
        return "pybullet"
    return want


def _compiled():
    """The compiled (rasterise, shade) kernels, or None where numba is not installed (then TinyRenderer renders)."""
    global _kernel
    if _kernel is None:
        try:
            import numba
        except ImportError:
            logger.warning("numba is not installed: the tiny backend renders with pybullet's TinyRenderer (~10x "
                           "slower rasterising, the same images); pip install numba for the compiled rasteriser")
            _kernel = False
            return None
        jit = numba.njit(cache=True, nogil=True)
        _kernel = (jit(_rasterise), jit(_shade))
    return _kernel or None


def _rasterise(clip, nrm, obj, size, depth, ids, normal):  # pragma: no cover - compiled by numba
    """Draw triangles `clip` (T, 3, 4: clip coordinates of each corner) into the buffers: `depth`
    (size × size, the nearest surface's eye distance, +inf where none), `ids` (its object) and
    `normal` (size × size × 3, its normal interpolated perspective-correctly, not normalised).
    Rows as TinyRenderer keeps them (y up): the caller flips them."""
    half = size / 2.0
    for t in range(clip.shape[0]):
        iw0, iw1, iw2 = 1.0 / clip[t, 0, 3], 1.0 / clip[t, 1, 3], 1.0 / clip[t, 2, 3]
        x0, y0 = clip[t, 0, 0] * iw0 * half + half, clip[t, 0, 1] * iw0 * half + half
        x1, y1 = clip[t, 1, 0] * iw1 * half + half, clip[t, 1, 1] * iw1 * half + half
        x2, y2 = clip[t, 2, 0] * iw2 * half + half, clip[t, 2, 1] * iw2 * half + half
        xmin = max(0.0, min(x0, min(x1, x2)))
        xmax = min(size - 1.0, max(x0, max(x1, x2)))
        ymin = max(0.0, min(y0, min(y1, y2)))
        ymax = min(size - 1.0, max(y0, max(y1, y2)))
        if xmin > xmax or ymin > ymax:
            continue
        ax, ay = x2 - x0, x1 - x0
        bx, by = y2 - y0, y1 - y0
        uz = ax * by - ay * bx
        if abs(uz) <= 1e-2:  # degenerate on screen: TinyRenderer throws it away
            continue
        for px in range(int(xmin), int(xmax) + 1):
            cx = x0 - px
            for py in range(int(ymin), int(ymax) + 1):
                cy = y0 - py
                ux = ay * cy - cx * by
                uy = cx * bx - ax * cy
                b1, b2 = uy / uz, ux / uz
                b0 = 1.0 - b1 - b2
                if b0 < 0.0 or b1 < 0.0 or b2 < 0.0:
                    continue
                c0, c1, c2 = b0 * iw0, b1 * iw1, b2 * iw2
                s = c0 + c1 + c2
                w = 1.0 / s  # the eye distance, interpolated perspective-correctly
                if w > depth[py, px]:
                    continue
                depth[py, px] = w
                ids[py, px] = obj[t]
                for k in range(3):
                    normal[py, px, k] = (c0 * nrm[t, 0, k] + c1 * nrm[t, 1, k] + c2 * nrm[t, 2, k]) / s


def world_triangles(geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray,
                    smooth: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every particle's triangles in the world (F, 3, 3, pybullet's cm), their corners' normals
    (F, 3, 3: the face's, or with `smooth` the vertices', as ``tiny.visual_meshes`` hands them to
    TinyRenderer: ``geometry.mesh_normals``) and each triangle's particle index (F,)."""
    n = len(geometry)
    nv, nf = np.diff(geometry.vert_offsets), np.diff(geometry.face_offsets)
    rot = quat_to_matrix(np.asarray(quats, float))
    v = np.einsum("vij,vj->vi", rot[np.repeat(np.arange(n), nv)], geometry.vertices.astype(np.float64) * CM)
    v += np.repeat(np.asarray(pos_mm, float) * CM, nv, axis=0)
    f = global_faces(geometry)
    normals = mesh_normals(v, f, smooth)
    corners = normals[f] if smooth else np.repeat(normals[:, None, :], 3, axis=1)
    return v[f], corners, np.repeat(np.arange(n), nf)


def _shade(ids, normal, colours, light, light_rgb, ambient, diffuse, specular, exponent, rgb):  # pragma: no cover
    """TinyRenderer's shader on every pixel: the object `ids`' colours (K × 3 in [0, 1]) lit along unit vector
    `light` → `rgb` (size × size × 3, float32 in [0, 1], in its byte steps): each channel
    min(255, floor(floor(255·colour) · (ambient + (diffuse·max(0, n·l) + specular·max(0, r_z)^exponent) · light))),
    r the light reflected about the normal n (the ambient light is white, the key light `light_rgb`)."""
    h, w = ids.shape
    for i in range(h):
        for j in range(w):
            nx, ny, nz = normal[i, j, 0], normal[i, j, 1], normal[i, j, 2]
            norm = math.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
            nx, ny, nz = nx / norm, ny / norm, nz / norm
            nl = nx * light[0] + ny * light[1] + nz * light[2]
            rx, ry, rz = 2 * nl * nx - light[0], 2 * nl * ny - light[1], 2 * nl * nz - light[2]
            rz = rz / (math.sqrt(rx * rx + ry * ry + rz * rz) + 1e-12)
            rz = max(rz, 0.0)
            spec = rz * rz if exponent == 2.0 else rz**exponent  # (a float power costs ~40 ns a pixel)
            lit = max(nl, 0.0) * diffuse + specular * spec
            k = ids[i, j]
            for c in range(3):
                byte = math.floor(math.floor(255.0 * colours[k, c]) * (ambient + lit * light_rgb[c]))
                rgb[i, j, c] = min(255.0, byte) / 255.0


def raster_raw(spec: dict, geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, p, look,
               camera: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What ``tiny.tiny_raw`` returns — (rgb float32 in [0, 1], ids int32 with 0 the table, height
    above the table in mm) at `supersample`× — drawn by the compiled rasteriser. `camera`: what
    ``camera_matrices`` gives (the matrices as pybullet's functions give them)."""
    kernel, shader = _compiled()
    size = p.resolution * p.supersample
    view, proj, _, _, height_cm = camera
    T = float(spec["table_size"])
    tri, nrm, pid = world_triangles(geometry, pos_mm, quats, spec["shape_type"] in ("granule", "ellipsoid"))
    # the table: the top of tiny.py's box (1.5x the table's half side), all the camera sees of it
    e, g = T / 2 * CM * 1.5, look.ground_level_mm * CM
    table = np.array([[[-e, -e, g], [e, -e, g], [e, e, g]], [[-e, -e, g], [e, e, g], [-e, e, g]]])
    tri = np.concatenate([table, tri])
    nrm = np.concatenate([np.tile([0.0, 0.0, 1.0], (2, 3, 1)), nrm])
    obj = np.concatenate([[0, 0], pid + 1]).astype(np.int32)
    to_clip = np.asarray(proj, float).reshape(4, 4).T @ np.asarray(view, float).reshape(4, 4).T
    clip = np.concatenate([tri, np.ones(tri.shape[:2] + (1,))], axis=2) @ to_clip.T
    depth = np.full((size, size), np.inf)
    ids = np.full((size, size), -1, np.int32)
    normal = np.zeros((size, size, 3), np.float32)
    kernel(np.ascontiguousarray(clip), np.ascontiguousarray(nrm), obj, size, depth, ids, normal)
    depth, ids, normal = depth[::-1], np.ascontiguousarray(ids[::-1]), normal[::-1]  # TinyRenderer's rows run upwards
    if (ids < 0).any():  # (the table fills every view: a pixel without it is a bug, not a look)
        raise RuntimeError("the rasteriser left pixels without a surface")
    colours = np.concatenate([[look.table_rgb], np.asarray(look.particle_rgb, float)])
    light = np.asarray(look.light_dir, float)
    rgb = np.empty((size, size, 3), np.float32)
    shader(ids, normal, colours, light / np.linalg.norm(light), np.asarray(look.light_rgb, float), float(look.ambient),
           float(look.light_intensity * (1 - look.ambient)), SPECULAR_COEFF, SPECULAR_EXPONENT, rgb)
    height_mm = np.clip((height_cm - depth) / CM, 0, None).astype(np.float32)
    return rgb, ids, height_mm


def camera_matrices(spec: dict, geometry: Geometry, pos_mm: np.ndarray, p, look) -> tuple:
    """(view, projection, near, far, camera height) in pybullet's cm, as the tiny backend sets its camera: a far
    camera over the table's centre whose field of view spans `view_fraction` of the table."""
    import pybullet as pb

    half = float(spec["table_size"]) / 2 * CM
    height = p.camera_height_mm * CM
    fov = math.degrees(2 * math.atan(half * look.view_fraction / height))
    top = float(np.nanmax(pos_mm[:, 2])) + float(geometry.dims_mm[:, 0].max()) if len(geometry) else 1.0
    near, far = height - (top * CM + 1.0), height + 1.0
    view = pb.computeViewMatrix([0, 0, height], [0, 0, 0], [0, 1, 0])
    proj = pb.computeProjectionMatrixFOV(fov, 1.0, near, far)
    return view, proj, near, far, height
