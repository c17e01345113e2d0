"""The dense size-histogram task of the CNN regressors (learn.size_cells)."""

import numpy as np
import pytest
import torch

from psdfactory import PsdError
from psdfactory.learn.augment import augment_d4, rescale
from psdfactory.learn.size_cells import (
    BIN_EDGES_LOG2_PX,
    N_CLASSES,
    CellHead,
    FeatureTap,
    cell_loss,
    cell_targets,
    code_classes,
    encode_log2_px,
    feature_channels,
    resize_codes,
    shift_codes,
    size_code_map,
)


def test_codes_are_log2_sizes_and_classes_are_half_octave_bins():
    codes = encode_log2_px(np.array([1.0, 2.0, 4.0, 45.3, np.nan, 0.0, 1e6]))
    assert codes.tolist()[:4] == [33, 49, 65, 33 + round(16 * np.log2(45.3))]
    assert codes[4] == codes[5] == 0 and codes[6] == 255  # unknown → table, huge → the last code
    classes = code_classes(torch.from_numpy(codes)).tolist()
    # 1 px is the first edge: bin 2 (bin 1 holds the sub-pixel sizes); 2 px two bins on; 4 px two more
    assert classes[:3] == [2, 4, 6] and classes[4] == 0 and classes[6] == N_CLASSES - 1
    assert N_CLASSES == len(BIN_EDGES_LOG2_PX) + 2


def test_the_code_map_gives_each_pixel_its_particles_size_and_targets_are_cell_shares():
    mask = np.zeros((8, 8), dtype=np.uint16)
    mask[:4, :4] = 1  # particle 0: 2 px sieve size
    mask[4:, 4:] = 2  # particle 1: 8 px
    codes = torch.from_numpy(size_code_map(mask, np.array([np.nan, 2.0, 8.0])))
    assert codes[0, 0] == 49 and codes[7, 7] == 81 and codes[0, 7] == 0
    t = cell_targets(codes[None], (2, 2))
    assert t.shape == (1, N_CLASSES, 2, 2)
    np.testing.assert_allclose(t.sum(dim=1), 1.0)
    assert t[0, 4, 0, 0] == 1.0 and t[0, 8, 1, 1] == 1.0 and t[0, 0, 0, 1] == 1.0
    with pytest.raises(PsdError, match="sizes are known for ids < 2"):
        size_code_map(mask, np.array([np.nan, 2.0]))


def test_halving_the_image_halves_the_sizes_and_magnifying_shifts_codes_exactly():
    codes = torch.tensor([[0, 81], [65, 97]], dtype=torch.uint8).repeat_interleave(4, 0).repeat_interleave(4, 1)
    half = resize_codes(codes, 4)
    assert half.shape == (4, 4) and half[0, 0] == 0 and half[0, 3] == 81 - 16 and half[3, 3] == 97 - 16
    assert shift_codes(codes, 2.0)[7, 7] == 97 + 16 and shift_codes(codes, 2.0)[0, 0] == 0


def test_d4_and_rescale_move_the_codes_with_the_image():
    gen = torch.Generator().manual_seed(3)
    img = torch.zeros(1, 4, 32, 32, dtype=torch.uint8)
    img[0, :3, :8, :4] = 200  # a bright particle in one corner ...
    img[0, 3, :8, :4] = 65  # ... whose code sits under it
    for _ in range(4):
        out = augment_d4(img, gen)
        assert torch.equal(out[0, 0] == 200, out[0, 3] == 65)
    img[0, :, 8:24, 8:24] = img[0, :, :1, :1]  # the same particle, large and central: in every crop
    out, y = rescale(img, torch.tensor([[1.0, 2.0, 3.0]]), (2.0, 2.0), gen)
    f = float(y[0, 0])
    bright, coded = out[0, 0] > 100, out[0, 3] > 0
    assert f == pytest.approx(2.0) and (bright == coded).float().mean() > 0.95
    assert set(out[0, 3][coded].tolist()) == {65 + 16}  # twice as large: one octave up
    out, y = rescale(img, torch.tensor([[1.0, 2.0, 3.0]]), (0.7, 0.7), gen)  # shrunk, the edges mirrored
    f = float(y[0, 0])
    bright, coded = out[0, 0] > 100, out[0, 3] > 0
    assert f < 0.75 and (bright == coded).float().mean() > 0.9  # all but the antialiased edges
    assert set(out[0, 3][coded].tolist()) == {65 + round(16 * np.log2(f))}


def test_the_head_reads_the_tapped_feature_map_and_learns_the_cells():
    import torchvision

    torch.manual_seed(0)
    model = torchvision.models.resnet18(weights=None, num_classes=3)
    tap = FeatureTap(model, "resnet18")
    head = CellHead(feature_channels(model, tap, 64))
    assert head.conv.in_channels == 512
    x = torch.randn(2, 3, 64, 64)
    model(x)
    assert tap.features.shape == (2, 512, 2, 2)
    codes = torch.full((2, 64, 64), 65, dtype=torch.uint8)
    target = cell_targets(codes, (2, 2))
    opt = torch.optim.Adam(head.parameters(), lr=0.05)
    feats = tap.features.detach()
    first = float(cell_loss(head(feats), target))
    for _ in range(30):
        loss = cell_loss(head(feats), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss) < first / 4
    tap.remove()
    with pytest.raises(PsdError, match="train.size_cells needs a CNN"):
        FeatureTap(torch.nn.Linear(2, 2), "linear")
