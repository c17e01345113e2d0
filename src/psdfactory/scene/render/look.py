"""What both render backends share: the render settings, the look drawn per scene (light,
particle and table colours and textures, the camera's field of view) so that both see the same
one, the camera's scale, and the sensor model that turns either backend's image into the final
8-bit RGB (JPEG compression included, as a camera's).

The look comes from two of the scene's random streams: ``render`` (the first settings, in their
original order, so that their draws stay the same) and ``look`` (the settings added since: each
drawn whatever the config says, so that switching one on changes no other draw)."""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ... import PsdError
from ...config import config_fields
from .cycles import CyclesParams, Range
from .distractors import DistractorParams
from .markings import MarkingParams

OCCLUSIONS = ("crevice", "sky")  # what the tiny backend darkens (tiny.shade_tiny)


@dataclass(frozen=True)
class RenderParams:
    """The config's `render` section (defaults: the schema's, config.schema.yaml)."""

    backend: str
    resolution: int
    supersample: int
    camera_height_mm: float
    # light: direction toward the light, drawn per scene
    light_azimuth_deg: Range
    light_elevation_deg: Range
    light_intensity: Range
    ambient: Range
    shadow_strength: Range
    occlusion_strength: Range
    occlusion: str  # crevice | sky: what the tiny backend darkens by occlusion_strength (tiny.shade_tiny)
    # materials
    palette: tuple[tuple[float, float, float], ...]
    particle_brightness: Range
    particle_hue_jitter: float
    surface_detail: Range  # texture amplitude, per particle
    particle_grain_mm: Range  # texture scale, per scene
    table_rgb: tuple[float, float, float]
    table_palette: tuple[tuple[float, float, float], ...]  # () = table_rgb
    table_hue_jitter: float
    table_brightness: Range
    table_texture: Range
    table_grain_mm: Range
    ground_level_mm: Range  # the table's (ground's) top above the bed's floor: buries the particles' feet
    light_tint: Range  # -1 cool … 0 white … 1 warm
    # camera / sensor
    view_fraction: Range  # side of the view / table side
    exposure: Range
    white_balance_jitter: float
    vignetting: Range
    blur_px: Range
    noise_sigma: Range  # read noise, fraction of full scale
    shot_noise: Range
    jpeg_fraction: float
    jpeg_quality: tuple[int, int]
    distractors: DistractorParams | None  # a scale card or ruler laid on the bed (distractors.py); None: off
    markings: MarkingParams | None  # veins, speckle, patches on the particles (markings.py); None: off
    # the Cycles backend's settings: None where another backend renders (config.render_params
    # leaves them out of that slice, so that editing them reruns nothing)
    cycles: CyclesParams | None

    @classmethod
    def from_dict(cls, d: dict) -> RenderParams:
        kw = config_fields(cls, {"cycles": None, "distractors": None, "markings": None, "occlusion": "crevice", **d},
                           "render")
        for k, v in kw.items():
            if k == "distractors":
                kw[k] = None if v is None else DistractorParams.from_dict(v)
            elif k == "markings":
                kw[k] = None if v is None else MarkingParams.from_dict(v)
            elif k == "cycles":
                if v is not None:
                    kw[k] = CyclesParams.from_dict(v)
                elif kw["backend"] == "cycles":
                    raise PsdError("render.backend 'cycles' needs the render.cycles settings in the slice")
            elif k == "occlusion" and v not in OCCLUSIONS:
                raise PsdError(f"render.occlusion must be one of {', '.join(OCCLUSIONS)}, got {v!r}")
            elif k in ("palette", "table_palette"):
                kw[k] = tuple(tuple(map(float, c)) for c in v)
            elif isinstance(v, list):
                kw[k] = tuple(v)
        return cls(**kw)


@dataclass
class Look:
    """The randomised look of one scene (recorded in render.json, bar the particle colours)."""

    light_dir: list[float]
    light_azimuth_deg: float
    light_elevation_deg: float
    light_intensity: float
    ambient: float
    shadow_strength: float
    occlusion_strength: float
    table_rgb: list[float]
    exposure: float
    white_balance: list[float]
    vignetting: float
    blur_px: float
    noise_sigma: float
    shot_noise: float
    # from the "look" stream
    view_fraction: float
    table_texture: float
    table_grain_mm: float
    ground_level_mm: float
    particle_grain_mm: float
    light_tint: float
    light_rgb: list[float]
    jpeg_quality: int | None  # None: no JPEG
    surface_detail: list[float]  # per particle
    particle_rgb: np.ndarray = field(repr=False)


# the key light's colour at tint +1 (warm, ~3500 K) and -1 (cool, ~8000 K), before normalising
WARM, COOL = np.array([1.0, 0.86, 0.68]), np.array([0.84, 0.92, 1.0])
LUMA = np.array([0.2126, 0.7152, 0.0722])


def tint_rgb(tint: float) -> list[float]:
    """The light's colour for a tint in [-1, 1], scaled to luminance 1 (the tint changes the
    colour, not the brightness)."""
    end = WARM if tint >= 0 else COOL
    rgb = 1 + abs(tint) * (end - 1)
    return (rgb / float(LUMA @ rgb)).tolist()


@dataclass(frozen=True)
class LookExtras:
    """The settings drawn from the "look" stream, in a fixed order."""

    view_fraction: float
    table_index: int
    table_hue: np.ndarray
    table_texture: float
    table_grain_mm: float
    ground_level_mm: float
    particle_grain_mm: float
    light_tint: float
    jpeg_quality: int | None
    surface_detail: np.ndarray


def draw_extras(rng: np.random.Generator, p: RenderParams, n: int) -> LookExtras:
    """Every draw is made whatever the settings (a range [x, x] or a fraction 0 still draws),
    so that changing one setting leaves every other draw as it was; per-particle draws last."""

    def u(r: Range) -> float:
        return float(rng.uniform(*r))

    view = u(p.view_fraction)
    table_index = int(rng.integers(max(len(p.table_palette), 1)))
    table_hue = 1 + rng.uniform(-p.table_hue_jitter, p.table_hue_jitter, size=3)
    texture, table_grain, ground, particle_grain, tint = (
        u(p.table_texture), u(p.table_grain_mm), u(p.ground_level_mm), u(p.particle_grain_mm), u(p.light_tint))
    jpeg = rng.random() < p.jpeg_fraction
    quality = int(rng.integers(p.jpeg_quality[0], p.jpeg_quality[1] + 1))
    detail = rng.uniform(*p.surface_detail, size=n)
    return LookExtras(view, table_index, table_hue, texture, table_grain, ground, particle_grain, tint,
                      quality if jpeg else None, detail)


def draw_look(rng: np.random.Generator, p: RenderParams, n: int, look_rng: np.random.Generator) -> Look:
    """The look of a scene of n particles: `rng` is the scene's "render" stream, `look_rng` its
    "look" stream (seeding.STREAMS)."""

    def u(r: Range) -> float:
        return float(rng.uniform(*r))

    # the "render" stream's draws, in their original order
    az, el = u(p.light_azimuth_deg), u(p.light_elevation_deg)
    a, e = math.radians(az), math.radians(el)
    light_dir = [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
    palette = np.asarray(p.palette, dtype=float)
    base = palette[rng.integers(len(palette), size=n)]
    bright = rng.uniform(*p.particle_brightness, size=(n, 1))
    hue = 1 + rng.uniform(-p.particle_hue_jitter, p.particle_hue_jitter, size=(n, 3))
    rgb = np.clip(base * bright * hue, 0.02, 1.0)
    table_brightness = u(p.table_brightness)
    wb = 1 + rng.uniform(-p.white_balance_jitter, p.white_balance_jitter, size=3)
    light_intensity, ambient, shadow, occlusion = (
        u(p.light_intensity), u(p.ambient), u(p.shadow_strength), u(p.occlusion_strength))
    exposure = u(p.exposure)
    vignetting, blur, noise, shot = u(p.vignetting), u(p.blur_px), u(p.noise_sigma), u(p.shot_noise)

    x = draw_extras(look_rng, p, n)
    table_base = np.asarray(p.table_palette[x.table_index] if p.table_palette else p.table_rgb)
    table = np.clip(table_base * table_brightness * x.table_hue, 0, 1)
    return Look(
        light_dir, az, el, light_intensity, ambient, shadow, occlusion, table.tolist(), exposure, wb.tolist(),
        vignetting, blur, noise, shot,
        view_fraction=x.view_fraction, table_texture=x.table_texture, table_grain_mm=x.table_grain_mm,
        ground_level_mm=x.ground_level_mm,
        particle_grain_mm=x.particle_grain_mm, light_tint=x.light_tint, light_rgb=tint_rgb(x.light_tint),
        jpeg_quality=x.jpeg_quality, surface_detail=np.round(x.surface_detail, 5).tolist(), particle_rgb=rgb,
    )


def mm_per_px(table_size_mm: float, resolution: int, view_fraction: float = 1.0) -> float:
    """The image's scale: the camera sees `view_fraction` of the table's side."""
    return table_size_mm * view_fraction / resolution


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """An 8-bit RGB image through JPEG compression at `quality` (PIL's libjpeg: 4:2:0 chroma)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


def apply_sensor(img: np.ndarray, look: Look, p: RenderParams, rng: np.random.Generator) -> np.ndarray:
    """The camera: exposure, white balance, vignetting, defocus, noise and JPEG → uint8 RGB."""
    r = p.resolution
    yy, xx = np.mgrid[0:r, 0:r]
    rad2 = ((xx - r / 2) ** 2 + (yy - r / 2) ** 2) / (r / 2) ** 2 / 2
    wb = np.asarray(look.white_balance, dtype=np.float32)
    img = img * look.exposure * wb * (1 - look.vignetting * rad2)[..., None]
    if look.blur_px > 0.05:
        img = ndimage.gaussian_filter(img, (look.blur_px, look.blur_px, 0))
    img = np.clip(img, 0, 1)
    noise = rng.standard_normal(img.shape).astype(np.float32)
    img = img + noise * np.sqrt(look.noise_sigma**2 + look.shot_noise * img)
    out = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
    return out if look.jpeg_quality is None else jpeg(out, look.jpeg_quality)
