"""The fast default render backend, ``tiny``: pybullet's TinyRenderer, CPU-only, whose cost is
per pixel. A far camera with a narrow field of view gives a metric top-down view of the
table's centre `view_fraction` of its side across, so ``mm_per_px = table_size * view / resolution``.
TinyRenderer has no anti-aliasing and no working cast shadows, so the image is supersampled
and shadows / contact occlusion are shaded afterwards from the depth buffer.
Mask values: 0 = table, k = particle_id + 1.

The triangles are drawn by ``raster.py``, a compiled copy of TinyRenderer's rasteriser and shader
(the same segmentation and heights, TinyRenderer's colour bytes bar a rare pixel; ~5x faster), or
with ``PSDFACTORY_RASTERISER=pybullet`` (and where numba is missing) by TinyRenderer itself.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..geometry import CM, Geometry, gc_paused, global_faces, mesh_normals
from .look import Look, RenderParams, mm_per_px
from .raster import SPECULAR_COEFF, camera_matrices, raster_raw
from .raster import rasteriser as raster_choice
from .sky import horizon_radius_mm, sky_view


def visual_meshes(geometry: Geometry, smooth: bool, scale: float) -> list[tuple[list, list, list]]:
    """Per particle (vertices, indices, normals) lists for pybullet, computed for all at once.

    Angular particles get unshared vertices with face normals (crisp facets); rounded ones
    share vertices with area-weighted vertex normals (smooth shading).
    """
    v = geometry.vertices.astype(np.float64) * scale
    f = global_faces(geometry)
    out = []
    if smooth:
        vn = mesh_normals(v, f, smooth=True)
        for i in range(len(geometry)):
            a, b = geometry.vert_offsets[i], geometry.vert_offsets[i + 1]
            local = geometry.faces[geometry.face_offsets[i] : geometry.face_offsets[i + 1]]
            out.append((v[a:b].tolist(), local.ravel().tolist(), vn[a:b].tolist()))
    else:
        fn = mesh_normals(v, f, smooth=False)
        tri = v[f].reshape(-1, 3)
        nrm = np.repeat(fn, 3, axis=0)
        for i in range(len(geometry)):
            a, b = 3 * geometry.face_offsets[i], 3 * geometry.face_offsets[i + 1]
            out.append((tri[a:b].tolist(), list(range(b - a)), nrm[a:b].tolist()))
    return out


def shade_from_height(height: np.ndarray, px_mm: float, light_dir: list[float], max_height_mm: float) -> np.ndarray:
    """Cast-shadow map (1 = in shadow) by marching each pixel toward the light over the height map."""
    lx, ly, lz = light_dir
    horiz = math.hypot(lx, ly)
    if horiz < 1e-6 or max_height_mm <= 0:
        return np.zeros_like(height)
    # image rows grow towards -y, columns towards +x
    dc, dr = lx / horiz, -ly / horiz
    rise_per_px = px_mm * lz / horiz  # height the ray gains per pixel travelled
    steps = int(min(max_height_mm / rise_per_px + 1, max(height.shape)))
    pad = steps + 1
    padded = np.pad(height, pad, mode="constant")
    h, w = height.shape
    shadow = np.zeros(height.shape, dtype=bool)
    for k in range(1, steps + 1):
        r0 = pad + int(round(k * dr))
        c0 = pad + int(round(k * dc))
        shadow |= padded[r0 : r0 + h, c0 : c0 + w] > height + k * rise_per_px + 0.3 * px_mm
    return shadow.astype(np.float32)


LINKS_PER_BODY = 127  # pybullet's segmentation value holds a link index + 1 in its top 7 bits

# the Gaussian sigmas of the texture's two octaves, in units of its grain (mm)
TEXTURE_OCTAVES = (0.4, 1.6)


def white_layers(rng: np.random.Generator, shape: tuple[int, int], n: int = len(TEXTURE_OCTAVES)) -> list[np.ndarray]:
    return [rng.standard_normal(shape).astype(np.float32) for _ in range(n)]


# an octave at least this smooth (Gaussian sigma, supersampled px) is made on the blocks the image is
# downsampled by, each block one value: what the downsampling would make of it (its blocks' means) but
# for a box blur far below its sigma, at a quarter of the filtering (2x supersampled: the texture's
# filters were a third of a paper scene's render)
COARSE_OCTAVE_SIGMA_PX = 3.0


def fractal_noise(layers: list[np.ndarray], sigmas_px: tuple[float, ...], block: int = 1) -> np.ndarray:
    """Octaves of smoothed white noise, summed and scaled to unit standard deviation: a grainy
    texture whose amplitude (table_texture, surface_detail) is the sd of the relative brightness.
    With `block` > 1 (the supersampling), an octave of sigma >= COARSE_OCTAVE_SIGMA_PX is smoothed
    on the white noise's block means, at sigma / block, and each block takes its value."""
    out = np.zeros(layers[0].shape, dtype=np.float32)
    for white, s in zip(layers, sigmas_px, strict=True):
        h, w = white.shape
        if block > 1 and s >= COARSE_OCTAVE_SIGMA_PX and h % block == 0 and w % block == 0:
            coarse = downsample(white, block)  # white noise again, of sd 1 / block
            layer = ndimage.gaussian_filter(coarse, s / block)
            layer = np.repeat(np.repeat(layer, block, axis=0), block, axis=1)
        else:
            layer = ndimage.gaussian_filter(white, s)
        out += layer / (layer.std() + 1e-6)
    return out / (out.std() + 1e-6)


def octaves_px(grain_mm: float, px_mm: float, supersample: int) -> tuple[float, ...]:
    return tuple(f * grain_mm / px_mm * supersample for f in TEXTURE_OCTAVES)


def tiny_raw(spec: dict, geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, p: RenderParams, look: Look,
             rasteriser: str | None = None):
    """TinyRenderer at `supersample`× → (rgb float32 in [0,1], ids int32, height above the table in mm), drawn by
    `rasteriser` (``raster.RASTERISERS``; default ``raster.rasteriser()``: the compiled one where numba imports)."""
    import pybullet as pb

    camera = camera_matrices(spec, geometry, pos_mm, p, look)
    if (rasteriser or raster_choice()) == "numba":
        return raster_raw(spec, geometry, pos_mm, quats, p, look, camera)
    with gc_paused():
        return _tiny_raw(pb, spec, geometry, pos_mm, quats, p, look, camera)


def _tiny_raw(pb, spec: dict, geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, p: RenderParams, look: Look,
              camera: tuple):
    n = len(geometry)
    T = float(spec["table_size"])
    size = p.resolution * p.supersample
    meshes = visual_meshes(geometry, smooth=spec["shape_type"] in ("granule", "ellipsoid"), scale=CM)

    cid = pb.connect(pb.DIRECT)
    try:
        half = T / 2 * CM
        table_vs = pb.createVisualShape(
            pb.GEOM_BOX, halfExtents=[half * 1.5, half * 1.5, 0.5], rgbaColor=[*look.table_rgb, 1], physicsClientId=cid
        )
        table = pb.createMultiBody(0, -1, table_vs, basePosition=[0, 0, look.ground_level_mm * CM - 0.5],
                                   physicsClientId=cid)
        # the particles as the links of a few multibodies: one call per LINKS_PER_BODY particles
        # instead of one each (measured: the render stage's CPU 0.96 -> 0.84 s a paper scene, the
        # image the same); a pixel's segmentation value is its body's id + (link index + 1) << 24,
        # in 32 bits: hence at most 127 links a body
        shapes = [pb.createVisualShape(pb.GEOM_MESH, vertices=verts, indices=idx, normals=normals,
                                       rgbaColor=[*look.particle_rgb[i], 1.0], specularColor=[0.05, 0.05, 0.05],
                                       physicsClientId=cid)
                  for i, (verts, idx, normals) in enumerate(meshes)]
        first = {}  # body id → its first particle
        for a in range(0, n, LINKS_PER_BODY):
            k = min(n - a, LINKS_PER_BODY)
            body = pb.createMultiBody(
                0, -1, -1, linkMasses=[0] * k, linkCollisionShapeIndices=[-1] * k,
                linkVisualShapeIndices=shapes[a:a + k], linkPositions=(pos_mm[a:a + k] * CM).tolist(),
                linkOrientations=quats[a:a + k].tolist(), linkInertialFramePositions=[[0, 0, 0]] * k,
                linkInertialFrameOrientations=[[0, 0, 0, 1]] * k, linkParentIndices=[0] * k,
                linkJointTypes=[pb.JOINT_FIXED] * k, linkJointAxis=[[0, 0, 1]] * k, physicsClientId=cid)
            first[body] = a

        view, proj, near, far, H = camera
        _, _, rgba, depth, seg = pb.getCameraImage(
            size,
            size,
            view,
            proj,
            lightDirection=look.light_dir,
            lightColor=look.light_rgb,  # the key light's; TinyRenderer keeps the ambient white
            lightDistance=100,
            shadow=0,
            lightAmbientCoeff=look.ambient,
            lightDiffuseCoeff=look.light_intensity * (1 - look.ambient),
            lightSpecularCoeff=SPECULAR_COEFF,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
            physicsClientId=cid,
        )
    finally:
        pb.disconnect(physicsClientId=cid)

    rgb = np.asarray(rgba, dtype=np.float32).reshape(size, size, 4)[..., :3] / 255.0
    depth = np.asarray(depth, dtype=np.float64).reshape(size, size)
    seg = np.asarray(seg).reshape(size, size)
    # table and background: 0; link j of a body whose first particle is a: particle a + j, id a + j + 1
    body, link = seg & 0xFFFFFF, seg >> 24
    lut = np.zeros(max(first, default=table) + 2, dtype=np.int64)
    for b, a in first.items():
        lut[b] = a
    hit = (seg >= 0) & (link > 0) & np.isin(body, list(first))
    ids = np.where(hit, lut[np.clip(body, 0, len(lut) - 1)] + link, 0).astype(np.int32)
    z_eye = far * near / (far - (far - near) * depth)
    height_mm = np.clip((H - z_eye) / CM, 0, None).astype(np.float32)
    return rgb, ids, height_mm


def render_tiny(spec: dict, geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, p: RenderParams,
                look: Look, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, dict]:
    """The fast backend → (rgb float32 HxWx3 in [0,1] before the sensor, uint16 mask, extra metadata)."""
    rgb, ids, height = tiny_raw(spec, geometry, pos_mm, quats, p, look)
    px_mm = mm_per_px(float(spec["table_size"]), p.resolution, look.view_fraction)
    radius = horizon_radius_mm(geometry.dims_mm) if len(geometry) else 1.0  # (render.occlusion: sky)
    rgb = shade_tiny(rgb, ids, height, look, p, px_mm, rng, radius)
    s = p.supersample
    mask = ids[s // 2 :: s, s // 2 :: s].astype(np.uint16)  # each block's centre sample: exact ids
    return rgb, mask, {"supersample": s}


def downsample(a: np.ndarray, s: int) -> np.ndarray:
    """Box-filter anti-aliasing: mean over s×s blocks."""
    if s == 1:
        return a
    out = a[::s, ::s].astype(np.float32 if a.dtype == np.float32 else np.float64)
    for i in range(s):  # block sums by strided adds: ~4x faster than a reshaped mean over two axes
        for j in range(s):
            if i or j:
                out += a[i::s, j::s]
    return out / (s * s)


def shade_tiny(rgb: np.ndarray, ids: np.ndarray, height: np.ndarray, look: Look, p: RenderParams, px_mm: float,
               rng: np.random.Generator, radius_mm: float = 1.0) -> np.ndarray:
    """Texture, anti-aliasing, cast shadows and occlusion for the TinyRenderer image; with
    `p.occlusion` 'sky', the sky a pixel does not see within `radius_mm` darkens it."""
    s = p.supersample
    # surface texture: the table's grain on table pixels, each particle's mottling on its own
    layers = white_layers(rng, ids.shape)
    table = ids == 0
    tex = np.where(table, fractal_noise(layers, octaves_px(look.table_grain_mm, px_mm, s), s),
                   fractal_noise(layers, octaves_px(look.particle_grain_mm, px_mm, s), s))
    amp = np.asarray([look.table_texture, *look.surface_detail], dtype=np.float32)[ids]
    rgb = rgb * (1 + amp * tex)[..., None]
    rgb = downsample(rgb, s)
    hgt = downsample(height, s)
    # cast shadows and contact / crevice occlusion from the height map
    shadow = shade_from_height(hgt, px_mm, look.light_dir, float(hgt.max()))
    shadow = ndimage.gaussian_filter(shadow, 0.8)
    if p.occlusion == "sky":
        occl = 1 - sky_view(hgt, px_mm, radius_mm)
    else:
        occl = np.clip((ndimage.gaussian_filter(hgt, 2.5 / px_mm) - hgt) / 3.0, 0, 1)
    light = (1 - look.shadow_strength * shadow) * (1 - look.occlusion_strength * occl)
    return rgb * light[..., None]
