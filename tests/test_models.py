import logging
import urllib.error

import pytest
import torch

from psdfactory import PsdError
from psdfactory.learn.models import OrderedHead, TargetStats, build_model, inception_aux_fits, input_size, main_output

STATS = TargetStats.from_targets(torch.tensor([[2.0, 8.0, 15.0], [3.0, 10.0, 16.0], [1.0, 7.0, 14.0]]))


def test_target_stats_standardise():
    y = torch.tensor([[2.0, 8.0, 15.0], [3.0, 10.0, 16.0], [1.0, 7.0, 14.0]])
    z = STATS.standardise(y)
    torch.testing.assert_close(z.mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    torch.testing.assert_close(z.std(0), torch.ones(3), atol=1e-6, rtol=0)


def test_ordered_head_always_ordered():
    head = OrderedHead(64, STATS)
    torch.nn.init.normal_(head.fc.weight, std=10.0)  # wild weights: order must still hold
    torch.nn.init.normal_(head.fc.bias, std=10.0)
    out = head(torch.randn(5000, 64) * 5)
    assert (out[:, 0] <= out[:, 1]).all() and (out[:, 1] <= out[:, 2]).all()


def test_head_starts_at_training_means():
    head = OrderedHead(8, STATS).eval()
    out = head(torch.zeros(1, 8))[0]
    torch.testing.assert_close(out, torch.tensor(STATS.mean, dtype=torch.float32), atol=1e-3, rtol=0)


@pytest.mark.parametrize("arch,size", [("resnet18", 64), ("efficientnet_b0", 64), ("mobilenet_v3_small", 64),
                                       ("inception_v3", 75)])
def test_models_regress_three_ordered_mm_values(arch, size):
    model, used = build_model(arch, STATS, "none", size=size)
    assert used.startswith("none")
    model.eval()
    with torch.no_grad():
        out = main_output(model(torch.randn(2, 3, size, size)))
    assert out.shape == (2, 3)
    assert (out[:, 0] <= out[:, 1]).all() and (out[:, 1] <= out[:, 2]).all()


@pytest.mark.slow
def test_inception_auxiliary_head_at_299():
    assert inception_aux_fits(299) and not inception_aux_fits(298)
    model, _ = build_model("inception_v3", STATS, "none", size=299)
    model.train()
    out = model(torch.randn(2, 3, 299, 299))
    assert out.logits.shape == (2, 3) and out.aux_logits.shape == (2, 3)
    small, _ = build_model("inception_v3", STATS, "none", size=160)
    small.train()
    assert main_output(small(torch.randn(2, 3, 160, 160))).shape == (2, 3)


def test_input_size_rules():
    assert input_size("inception_v3") == 299 and input_size("resnet50") == 224
    assert input_size("resnet50", {"resnet50": 128}) == 128
    with pytest.raises(PsdError, match="below the 75 px"):
        input_size("inception_v3", {"inception_v3": 64})


def test_unknown_architecture():
    with pytest.raises(PsdError, match="unknown architecture"):
        build_model("resnet5000", STATS)


def test_imagenet_weights_unavailable(monkeypatch, caplog):
    def offline(*a, **k):
        raise urllib.error.URLError("no network")

    import torchvision.models._api as api

    monkeypatch.setattr(api, "load_state_dict_from_url", offline)  # as if offline with an empty cache
    with pytest.raises(PsdError, match="could not be had"):
        build_model("resnet18", STATS, "imagenet")
    with pytest.warns(UserWarning, match="training from scratch"):
        _, used = build_model("resnet18", STATS, "auto")
    warned = [r for r in caplog.records if r.name == "psdfactory.learn.models" and r.levelno == logging.WARNING]
    assert "unavailable" in used and warned and "training from scratch" in warned[0].getMessage()
