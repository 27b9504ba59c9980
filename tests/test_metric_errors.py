"""The per-sample errors the accept rule's error-decrease test compares are
those of the loop's metric (diagnose.metric.metric_errors)."""

from types import SimpleNamespace

import numpy as np

from bondgraph.diagnose.metric import compute_metric, metric_errors
from bondgraph.diagnose.settings import LoopSettings


class _Rec:
    def __init__(self, y):
        self.y = y

    def arrays(self, model):
        return np.arange(len(self.y)), np.zeros((len(self.y), 1)), self.y


def _fit(y, sim_y):
    innov = (y - sim_y)[:, None, :] * 0.5
    return SimpleNamespace(model=None, sim_y=sim_y, ukf=SimpleNamespace(innovations=innov))


def test_builtin_metrics_give_their_own_errors():
    rng = np.random.default_rng(1)
    y = rng.normal(0, [2.0, 0.5], (200, 2))
    sim = y + rng.normal(0, 0.1, (200, 2))
    rec, fit = _Rec(y), _fit(y, sim)
    e = metric_errors(LoopSettings(params=["a"], metric="nrmse_sim"), fit, rec)
    # hand-derived: each output's error over the std of its measurement
    np.testing.assert_allclose(e, (y - sim) / y.std(axis=0), rtol=1e-12)
    # the metric is the mean over outputs of the RMS of these errors
    assert compute_metric(LoopSettings(params=["a"], metric="nrmse_sim"), fit, rec) == \
        np.mean(np.sqrt(np.mean(e**2, axis=0)))
    ep = metric_errors(LoopSettings(params=["a"], metric="rmse_pred"), fit, rec)
    np.testing.assert_allclose(ep, 0.5 * (y - sim), rtol=1e-12)


def test_a_callable_metric_without_errors_gives_none_with_errors_its_own():
    y = np.ones((10, 1))
    fit = _fit(y, y)

    def plain(f, r):
        return 1.0

    class WithErrors:
        def __call__(self, f, r):
            return 1.0

        def errors(self, f, r):
            return np.full((10, 1), 3.0)

    assert metric_errors(LoopSettings(params=["a"], metric=plain), fit, _Rec(y)) is None
    np.testing.assert_array_equal(metric_errors(LoopSettings(params=["a"], metric=WithErrors()), fit, _Rec(y)),
                                  np.full((10, 1), 3.0))
