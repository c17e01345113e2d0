import numpy as np
import pytest

from psdfactory.learn.metrics import r2, regression_metrics


def test_r2_hand_computed():
    assert r2(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 4.0])) == pytest.approx(0.5)  # 1 - 1/2
    assert r2(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0])) == 1.0
    assert r2(np.array([1.0, 2.0, 3.0]), np.array([2.0, 2.0, 2.0])) == pytest.approx(0.0)
    assert np.isnan(r2(np.array([2.0, 2.0]), np.array([1.0, 3.0])))


def test_regression_metrics_table_layout():
    y = np.array([[1.0, 5.0, 10.0], [2.0, 6.0, 12.0]])
    p = np.array([[1.5, 5.0, 10.0], [2.0, 5.0, 13.0]])
    m = regression_metrics(y, p)
    assert m["n"] == 2
    assert m["d10"]["mae"] == pytest.approx(0.25)
    assert m["d10"]["mse"] == pytest.approx(0.125)
    assert m["d10"]["r2"] == pytest.approx(1 - 0.25 / 0.5)
    assert m["d50"]["rel_err"] == pytest.approx((0 + 1 / 6) / 2)
    assert m["d90"]["mae"] == pytest.approx(0.5)
    # overall pools the six numbers
    err = (p - y).ravel()
    assert m["overall"]["mse"] == pytest.approx((err**2).mean())
    yy = y.ravel()
    assert m["overall"]["r2"] == pytest.approx(1 - (err**2).sum() / ((yy - yy.mean()) ** 2).sum())
    assert m["mean_r2"] == pytest.approx(np.mean([m[k]["r2"] for k in ("d10", "d50", "d90")]))
    assert m["order_violations"] == 0.0


def test_order_violations_counted():
    y = np.ones((4, 3))
    p = np.array([[1, 2, 3], [2, 1, 3], [1, 3, 2], [1, 1, 1]], dtype=float)
    assert regression_metrics(y, p)["order_violations"] == pytest.approx(0.5)


def test_paired_r2_gain_hand_computed():
    from psdfactory.learn.metrics import paired_r2_gain

    y = np.array([[0.0], [1.0], [2.0], [3.0]])  # total sum of squares 5
    a = y + np.array([[1.0], [-1.0], [1.0], [-1.0]])  # squared errors 1, 1, 1, 1
    b = y + np.array([[0.0], [0.0], [1.0], [-1.0]])  # 0, 0, 1, 1
    gain, se = paired_r2_gain(y, a, b)
    assert gain == pytest.approx([2.0 / 5.0])  # (1 + 1 + 0 + 0) / 5
    d = np.array([1.0, 1.0, 0.0, 0.0])
    assert se == pytest.approx([np.sqrt(4) * d.std(ddof=1) / 5.0])
    gain_ba, se_ba = paired_r2_gain(y, b, a)
    assert gain_ba == pytest.approx(-gain) and se_ba == pytest.approx(se)
    flat, _ = paired_r2_gain(np.ones((4, 1)), a, b)
    assert np.isnan(flat).all()  # a constant target has no R²


def test_cross_validated_r2_is_r2_of_the_out_of_fold_predictions():
    from psdfactory.learn.metrics import cross_validated_r2, out_of_fold, r2_scores

    rng = np.random.default_rng(3)
    x = rng.normal(size=(30, 2))
    y = x @ [[1.0], [2.0]] + rng.normal(size=(30, 1)) * 0.1
    oof = out_of_fold(x, y, folds=5, ridge=1e-3)
    assert cross_validated_r2(x, y, folds=5, ridge=1e-3) == pytest.approx(r2_scores(y, oof))
    assert 0.9 < r2_scores(y, oof)[0] < 1.0  # out of fold: good but not perfect
