"""The report's accuracy table: ceilings lead, per-target R² as a fraction of them, re-render columns."""

from psdfactory.report import accuracy_table, rerenders_of

from .conftest import tiny_config


def _metrics(r2s):
    per = {n: {"r2": r, "mse": 1.0, "mae": 0.5, "rel_err": 0.1} for n, r in zip(("d10", "d50", "d90"), r2s)}
    return {**per, "overall": {"r2": 0.98, "mse": 1.0, "mae": 0.5}, "order_violations": 0.0}


def test_accuracy_table_shows_fractions_of_the_ceiling_and_the_rerender_column():
    metrics = {"net": {"datasets": {"train": _metrics([0.36, 0.90, 0.49]), "again": _metrics([-0.5, 0.45, 0.2])}}}
    ceiling = {"visible": {"d10_mm": 0.72, "d50_mm": 0.95, "d90_mm": 0.98}, "sampling": None}
    head, rows = accuracy_table(metrics, "train", ceiling, {"again": "Cycles (again)"})
    assert head[:4] == ["model", "R² d10 (of ceiling)", "R² d50 (of ceiling)", "R² d90 (of ceiling)"]
    assert head[4:7] == [f"R² {n} on Cycles (again) renders" for n in ("d10", "d50", "d90")]
    assert rows[0][:4] == ["ceiling: true sizes of the visible particles", "0.720", "0.950", "0.980"]
    net = rows[1]
    assert net[:4] == ["net", "0.360 (50 %)", "0.900 (95 %)", "0.490 (50 %)"]
    assert net[4:7] == ["-0.500 (-69 %)", "0.450 (47 %)", "0.200 (20 %)"]
    assert all(len(r) == len(head) for r in rows)
    # no ceiling known: plain R², no ceiling row
    head, rows = accuracy_table(metrics, "train")
    assert rows[0][1] == "0.360" and len(rows) == 1


def test_rerenders_are_found_and_named_by_their_renderer():
    cfg = tiny_config(n_scenes=8, split={"train": 0.5, "val": 0.25, "test": 0.25})
    cfg["datasets"]["again"] = {"rerender_of": {"dataset": "tiny"}, "render": {"backend": "cycles"}}
    assert rerenders_of(cfg, "tiny") == {"again": "Cycles (again)"}
    assert rerenders_of(cfg, "again") == {}
