"""A third estimator, as an outside package would add one (tests only): d10/d50/d90 read by a
linear map from an image's mean colour. It is declared in the ``psdfactory.estimators``
entry-point group (``psd_meancolour-0.1.dist-info/entry_points.txt`` beside this file: a folder on
PYTHONPATH makes it installed), and psdfactory trains, evaluates, benchmarks, reports, predicts
with and exports it through `learn.estimator.Estimator` alone."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import nn

from psdfactory.learn.data import SceneImages, label_definition, normalise, training_rows
from psdfactory.learn.estimator import Estimator, Reading
from psdfactory.learn.fit import FitTask, fingerprint, fit, write_history
from psdfactory.learn.runtime import LrSchedule, save_model
from psdfactory.psd import TARGETS


class MeanColourNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.fc = nn.Linear(3, len(TARGETS))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(x.mean(dim=(2, 3)))


class MeanColour(Estimator):
    int8 = False

    @classmethod
    def build_net(cls, meta: dict) -> nn.Module:
        return MeanColourNet()

    def read(self, outputs: np.ndarray, mm_per_px: list[float]) -> list[Reading]:
        return [Reading(np.sort(np.asarray(o, dtype=float))) for o in outputs]

    @classmethod
    def train(cls, params, results_root: Path, out_dir: Path, settings: dict | None = None) -> dict:
        torch.manual_seed(params.seed)
        size = params.input_size
        train_rows, val_rows, rows = training_rows(results_root, params.datasets)
        tr, va = SceneImages(results_root, train_rows, size), SceneImages(results_root, val_rows, size)
        xt = normalise(torch.stack([tr[i][0] for i in range(len(tr))]))
        xv = normalise(torch.stack([va[i][0] for i in range(len(va))]))
        net = MeanColourNet()
        with torch.no_grad():
            net.fc.bias.copy_(tr.y.mean(dim=0))
        opt = torch.optim.Adam(net.parameters(), lr=0.05)
        sched = LrSchedule(opt, "plateau", params.epochs, 1, 0.5, 2)

        def epoch(bar) -> float:
            loss = nn.functional.mse_loss(net(xt), tr.y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            bar.update(len(xt))
            return float(loss)

        def validate() -> dict:
            with torch.no_grad():
                p = net(xv)
            return {"val_loss": float(nn.functional.mse_loss(p, va.y)), "val_mae_mm": float((p - va.y).abs().mean())}

        meta = {"arch": params.arch, "input_size": size, "image_resolution": int(train_rows[0]["resolution"]),
                "mm_per_px": float(train_rows[0]["mm_per_px"]), "weights": "none (closed form)",
                "targets": list(TARGETS), **label_definition(rows), "params": asdict(params)}
        res = fit(FitTask(net, opt, sched, epoch, validate, len(xt)), params.arch, params.epochs,
                  params.early_stopping_patience, out_dir, fingerprint(asdict(params), [r["scene_id"] for r in rows]),
                  meta)
        summary = {**meta, "best_epoch": res.best_epoch, "epochs_run": len(res.history), "precision": "fp32"}
        save_model(out_dir / "model.pt", net, summary)
        write_history(res.history, out_dir / "history.csv")
        return summary
