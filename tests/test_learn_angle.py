"""The force-angle fixes of issue 19 (docs/learn.md, "Why the angle error was large")."""

import numpy as np
import torch

from learn.metrics import ANGLE_MIN_FORCE
from learn.normalize import MinMax
from learn.train import NeuralEstimator, TrainConfig


def test_quantile_scaling_maps_the_central_range_to_unit_and_ignores_the_tail() -> None:
    rng = np.random.default_rng(0)
    bulk = rng.uniform(-1.0, 1.0, size=(10_000, 3))
    values = np.vstack([bulk, np.full((20, 3), 50.0)])  # 0.2 % bottoming-out rows at 50 N
    scale = MinMax.fit_quantile(values, 0.01)
    # U(-1, 1): the 1 % and 99 % quantiles are -0.98 and 0.98 (+- sampling error ~0.003)
    np.testing.assert_allclose(scale.low, -0.98, atol=0.01)
    np.testing.assert_allclose(scale.low + scale.span, 0.98, atol=0.01)
    assert MinMax.fit(values).span[0] > 50.0  # min-max: the bulk would fill < 4 % of [0, 1]
    np.testing.assert_allclose(MinMax.fit_quantile(values, 0.0).span, MinMax.fit(values).span)


def test_angle_loss_is_one_minus_cosine_over_rows_above_the_threshold() -> None:
    est = NeuralEstimator(TrainConfig(angle_weight=1.0))
    est.target_scales = {"force": MinMax(low=np.array([-5.0, -5.0, -5.0]), span=np.array([10.0, 10.0, 10.0]))}
    true = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.1, 0.0, 0.0]])  # last row below 0.5 N: ignored
    pred = np.array([[1.0, 1.0, 0.0], [0.0, -3.0, 0.0], [-4.0, 0.0, 0.0]])
    scaled = [torch.as_tensor((f + 5.0) / 10.0, dtype=torch.float64) for f in (pred, true)]
    expected = np.mean([1.0 - np.cos(np.pi / 4.0), 2.0])  # 45 degrees and opposite
    assert np.linalg.norm(true[2]) < ANGLE_MIN_FORCE
    np.testing.assert_allclose(float(est._angle_loss(*scaled)), expected, rtol=1e-9)
