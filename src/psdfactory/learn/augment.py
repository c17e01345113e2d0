"""Training augmentations that keep the labels true.

- ``augment_d4``: 90° rotations and flips — a top-down bed has no preferred orientation.
- ``rescale``: magnify or shrink an image by s at the same mm per pixel. Every particle then
  looks s times larger (or smaller), so the labels in mm are multiplied by s — exact up to the
  pixel rounding of the crop (the factor applied is the one the integer crop really gives).
  Magnifying crops the centre-ish of the bed (a random window of side S/s, resized to S); shrinking
  resizes to S·s and fills the frame by mirroring the image at its edges (the bed goes on).
- ``photometric``: what a camera and its light do to an image but not to the particles — gain,
  contrast, gamma, white balance, colour saturation, a grey image, blur and sensor noise — so a
  model learns sizes, not one renderer's colours.
- ``surface_texture``: speckle, mottling and veins laid on the grains (the foreground) of an image,
  as natural stones carry them, so that a grain finder learns that an edge inside a grain's
  texture is not a grain's edge.
- ``grain_colour``: each grain of an image given a colour and brightness of its own, as the pebbles
  of a river bed or a beach differ stone by stone, so that a grain finder learns what a grain is
  from its shape and edges, not from the few rock colours it was rendered in.

All take and return uint8 N×3×S×S batches (rescale also the N×3 labels, and a fourth channel of
size codes, `size_cells`, with d4 and rescale), draw from a
``torch.Generator`` (reproducible), and run per image on the CPU in a few ms.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn import functional as F

# test-time augmentation (e.g. train.instances.tta): the maps averaged over these views of the image,
# each (quarter turns, mirrored) and turned back — the symmetries the training crops are drawn
# under, so each view is an image of the kind the network learnt
TTA_VIEWS = {
    "none": ((0, False),),
    "flips": ((0, False), (0, True), (2, False), (2, True)),
    "d4": tuple((k, flip) for k in range(4) for flip in (False, True)),
}


def view(x: torch.Tensor, k: int, flip: bool) -> torch.Tensor:
    """`x` (…×H×W) turned by k quarter turns, then mirrored left-right with `flip`: an element of
    the dihedral group of the square."""
    x = torch.rot90(x, k, dims=(-2, -1))
    return torch.flip(x, dims=(-1,)) if flip else x


def unview(x: torch.Tensor, k: int, flip: bool) -> torch.Tensor:
    """The inverse of `view`: maps of a viewed image back in the image's own frame."""
    x = torch.flip(x, dims=(-1,)) if flip else x
    return torch.rot90(x, -k, dims=(-2, -1))


def augment_d4(batch: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random 90° rotations and flips (the dihedral group of the square), per image."""
    out = torch.empty_like(batch)
    k = torch.randint(0, 4, (len(batch),), generator=gen)
    flip = torch.randint(0, 2, (len(batch),), generator=gen)
    for i in range(len(batch)):
        out[i] = view(batch[i], int(k[i]), bool(flip[i]))
    return out


def _resize(img: torch.Tensor, size: int) -> torch.Tensor:
    """float 3×H×W → 3×size×size (antialiased bilinear)."""
    return F.interpolate(img[None], size=(size, size), mode="bilinear", antialias=True, align_corners=False)[0]


def rescale_one(img: torch.Tensor, s: float, gen: torch.Generator) -> tuple[torch.Tensor, float]:
    """One uint8 C×S×S image magnified by about `s` (same size out) → (image, the exact factor).
    A fourth channel is a size-code map (`size_cells`): cropped and padded as the image, resized
    by nearest neighbour and its codes shifted by the factor."""
    from .size_cells import shift_codes

    size = img.shape[-1]
    codes = img[3:4].float() if img.shape[0] == 4 else None
    x = img[:3].float()
    if s >= 1.0:
        c = max(8, min(size, round(size / s)))
        r0, c0 = (int(torch.randint(0, size - c + 1, (1,), generator=gen)) for _ in range(2))
        out = _resize(x[:, r0 : r0 + c, c0 : c0 + c], size)
        factor = size / c
        if codes is not None:
            codes = F.interpolate(codes[None, :, r0 : r0 + c, c0 : c0 + c], size=(size, size), mode="nearest")[0]
    else:
        r = max(8, min(size, round(size * s)))
        small = _resize(x, r)
        pad = size - r
        top, left = (int(torch.randint(0, pad + 1, (1,), generator=gen)) for _ in range(2))
        # mirrored at the edges: one reflection suffices for s > 1/2 (each pad is shorter than r)
        out = F.pad(small[None], (left, pad - left, top, pad - top), mode="reflect")[0]
        factor = r / size
        if codes is not None:
            codes = F.interpolate(codes[None], size=(r, r), mode="nearest")
            codes = F.pad(codes, (left, pad - left, top, pad - top), mode="reflect")[0]
    out = out.round().clamp(0, 255).to(torch.uint8)
    if codes is not None:
        out = torch.cat([out, shift_codes(codes.to(torch.uint8), factor)])
    return out, factor


def rescale(batch: torch.Tensor, y_mm: torch.Tensor, scale: tuple[float, float],
            gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Each image magnified by s, log-uniform in [lo, hi] (1/2 < lo ≤ hi), and its labels
    multiplied by the factor the crop really applies."""
    lo, hi = scale
    if not 0.5 < lo <= hi:
        raise ValueError(f"scale range {scale}: needs 1/2 < lo <= hi")
    if lo == hi == 1.0:
        return batch, y_mm
    u = torch.rand(len(batch), generator=gen)
    s = torch.exp(torch.log(torch.tensor(lo)) + u * (torch.log(torch.tensor(hi)) - torch.log(torch.tensor(lo))))
    out = torch.empty_like(batch)
    y = y_mm.clone()
    for i in range(len(batch)):
        out[i], f = rescale_one(batch[i], float(s[i]), gen)
        y[i] = y_mm[i] * f
    return out, y


def photometric(batch: torch.Tensor, gen: torch.Generator, strength: float = 1.0) -> torch.Tensor:
    """Camera and light changes, drawn per image; `strength` 0 = none, 1 = the default ranges."""
    if strength <= 0:
        return batch
    n = len(batch)

    def u(lo: float, hi: float, shape=(n,)) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(shape, generator=gen)

    x = batch.float() / 255.0
    gain = torch.exp(u(-0.5, 0.5) * strength).view(n, 1, 1, 1)
    wb = torch.exp(u(-0.15, 0.15, (n, 3)) * strength).view(n, 3, 1, 1)
    x = x * gain * wb
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = mean + (x - mean) * torch.exp(u(-0.4, 0.4) * strength).view(n, 1, 1, 1)  # contrast
    grey = x.mean(dim=1, keepdim=True)
    sat = torch.exp(u(-1.0, 0.7) * strength).view(n, 1, 1, 1)
    x = grey + (x - grey) * sat
    to_grey = (torch.rand(n, generator=gen) < 0.2 * strength).view(n, 1, 1, 1)
    x = torch.where(to_grey, x.mean(dim=1, keepdim=True).expand_as(x), x)
    x = x.clamp(0, 1) ** torch.exp(u(-0.4, 0.4) * strength).view(n, 1, 1, 1)  # gamma
    sigma = u(0.0, 1.2 * strength)
    for i in range(n):  # defocus: a small Gaussian blur, some images only
        if sigma[i] > 0.4:
            k = torch.arange(-2, 3, dtype=torch.float32)
            w = torch.exp(-(k**2) / (2 * float(sigma[i]) ** 2))
            w = (w / w.sum()).view(1, 1, 1, 5)
            xi = x[i : i + 1].transpose(0, 1)  # 3×1×H×W: one channel at a time
            xi = F.conv2d(F.pad(xi, (2, 2, 0, 0), mode="reflect"), w)
            xi = F.conv2d(F.pad(xi, (0, 0, 2, 2), mode="reflect"), w.transpose(2, 3))
            x[i] = xi.transpose(0, 1)[0]
    noise = u(0.0, 0.03 * strength).view(n, 1, 1, 1)
    x = x + noise * torch.randn(x.shape, generator=gen)
    return (x.clamp(0, 1) * 255.0).round().to(torch.uint8)


# surface_texture's ranges at strength 1: the texture's cell (px, log-uniform), its contrast (sd of the relative
# brightness change), the share of images it is laid on, and the veins' share of those, contrast and width (px)
TEXTURE_CELL_PX = (1.5, 8.0)
TEXTURE_CONTRAST = (0.05, 0.35)
TEXTURE_SHARE = 0.5
VEIN_SHARE = 0.5
VEIN_CONTRAST = (0.2, 0.5)
VEIN_WIDTH_PX = (0.6, 1.5)


def noise_field(size: tuple[int, int], cell_px: float, gen: torch.Generator) -> torch.Tensor:
    """H×W band-limited noise: white noise on a grid of `cell_px`-px cells, bilinearly interpolated,
    at a random sub-cell offset; zero mean and unit sd over the field."""
    h, w = size
    gh, gw = math.ceil(h / cell_px) + 2, math.ceil(w / cell_px) + 2
    coarse = torch.randn((1, 1, gh, gw), generator=gen)
    big = F.interpolate(coarse, size=(round(gh * cell_px), round(gw * cell_px)), mode="bilinear", align_corners=False)
    r0, c0 = (int(torch.randint(0, max(int(cell_px), 1), (1,), generator=gen)) for _ in range(2))
    field = big[0, 0, r0 : r0 + h, c0 : c0 + w]
    return (field - field.mean()) / field.std().clamp_min(1e-6)


def surface_texture(batch: torch.Tensor, foreground: torch.Tensor, gen: torch.Generator,
                    strength: float = 1.0) -> torch.Tensor:
    """Texture on the grains of a share (TEXTURE_SHARE) of the images of a uint8 N×3×H×W batch:
    each such image's pixels where `foreground` (N×H×W, > 0.5: a grain) are multiplied by
    1 + a·n (n: `noise_field` of a drawn cell size, plus its octave at half the cell and half the
    weight; a: the texture's drawn contrast × `strength`), and on half of them by thin veins, light
    or dark (the zero line of a smoother field). The field runs on across touching grains, so it
    marks no grain's edge; the labels do not change. `strength` 0 = none, 1 = the default ranges."""
    if strength <= 0:
        return batch
    n, _, h, w = batch.shape

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((1,), generator=gen))

    out = batch.clone()
    for i in range(n):
        if float(torch.rand((1,), generator=gen)) >= TEXTURE_SHARE:
            continue
        cell = math.exp(u(*(math.log(c) for c in TEXTURE_CELL_PX)))
        field = noise_field((h, w), cell, gen) + 0.5 * noise_field((h, w), max(cell / 2, 1.0), gen)
        gain = 1.0 + u(*TEXTURE_CONTRAST) * strength * field / math.hypot(1.0, 0.5)  # the sum's sd
        if float(torch.rand((1,), generator=gen)) < VEIN_SHARE:
            smooth = noise_field((h, w), cell * u(3.0, 6.0), gen)
            slope = torch.stack(torch.gradient(smooth)).norm(dim=0).clamp_min(1e-3)
            vein = torch.exp(-((smooth / slope / u(*VEIN_WIDTH_PX)) ** 2))  # ~1 on the zero line, width in px
            gain = gain * (1.0 + (1 if float(torch.rand((1,), generator=gen)) < 0.5 else -1)
                           * u(*VEIN_CONTRAST) * strength * vein)
        grain = foreground[i] > 0.5
        x = out[i].float() * torch.where(grain, gain.clamp_min(0.0), torch.ones_like(gain))
        out[i] = x.round().clamp(0, 255).to(torch.uint8)
    return out


# grain_colour's ranges at strength 1: the share of images it recolours, and the log-range of each grain's
# factor per channel (its colour cast) and overall (its brightness)
GRAIN_COLOUR_SHARE = 0.5
GRAIN_CAST = 0.2
GRAIN_BRIGHTNESS = 0.4


def grain_regions(foreground: torch.Tensor, boundary: torch.Tensor) -> np.ndarray:
    """The grains of one crop (H×W maps, > 0.5 on) as integer labels: the foreground without its
    boundary pixels, split into connected parts, and each foreground pixel of the boundary given the
    label of the nearest part (0 = the table)."""
    from scipy import ndimage

    fg = foreground.numpy() > 0.5
    cores, n = ndimage.label(fg & ~(boundary.numpy() > 0.5))
    if n == 0:
        return cores
    _, (rows, cols) = ndimage.distance_transform_edt(cores == 0, return_indices=True)
    return np.where(fg, cores[rows, cols], 0)


def grain_colour(batch: torch.Tensor, foreground: torch.Tensor, boundary: torch.Tensor, gen: torch.Generator,
                 strength: float = 1.0) -> torch.Tensor:
    """Each grain of a share (GRAIN_COLOUR_SHARE) of the images of a uint8 N×3×H×W batch multiplied
    by a colour of its own: a factor exp(U(-c, c)) per channel (c = GRAIN_CAST × `strength`) times a
    brightness exp(U(-b, b)) (b = GRAIN_BRIGHTNESS × `strength`). The grains are those of the crop's
    own targets (`foreground`, `boundary`: N×H×W, `grain_regions`), so touching grains part where
    they meet and a grain's colour stops at its edge; the table and the labels do not change.
    `strength` 0 = none, 1 = the default ranges."""
    if strength <= 0:
        return batch
    out = batch.clone()
    cast, bright = GRAIN_CAST * strength, GRAIN_BRIGHTNESS * strength
    for i in range(len(batch)):
        if float(torch.rand((1,), generator=gen)) >= GRAIN_COLOUR_SHARE:
            continue
        regions = torch.from_numpy(grain_regions(foreground[i], boundary[i])).long()
        n = int(regions.max())
        if n == 0:
            continue
        factors = torch.exp((torch.rand((n, 3), generator=gen) * 2 - 1) * cast
                            + (torch.rand((n, 1), generator=gen) * 2 - 1) * bright)
        gain = torch.cat([torch.ones(1, 3), factors])[regions].permute(2, 0, 1)  # 3×H×W, 1 on the table
        out[i] = (out[i].float() * gain).round().clamp(0, 255).to(torch.uint8)
    return out
