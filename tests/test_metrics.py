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
