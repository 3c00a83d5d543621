"""Metrics: wrapped yaw errors, strict recalls, APE/AOE means and the paper's table layout."""

import math

import numpy as np
import pytest

from seglocnet_jax import metrics


def test_yaw_error_wraps_and_is_in_degrees():
    pred = np.array([[0.0, 0.0, math.radians(179)], [0.0, 0.0, math.pi]])
    gt = np.array([[3.0, 4.0, math.radians(-179)], [0.0, 0.0, -math.pi]])
    pos, yaw = metrics.pose_errors(pred, gt)
    np.testing.assert_allclose(pos, [5.0, 0.0])
    np.testing.assert_allclose(yaw, [2.0, 0.0], atol=1e-9)


def test_recall_is_strict():
    assert metrics.recall([1.0, 0.5, 2.0, 0.999], 1.0) == 50.0
    assert metrics.recall([1.0], 1.0) == 0.0
    assert math.isnan(metrics.recall([], 1.0))


def test_summary_of_hand_computed_errors():
    pos = np.array([0.5, 1.0, 1.5, 4.0, 12.0])  # metres
    yaw = np.array([0.2, 2.0, 1.0, 9.0, 30.0])  # degrees
    r = metrics.summarize(pos, yaw)
    assert r == {
        "R@1m": 20.0,
        "R@2m": 60.0,
        "R@5m": 80.0,
        "R@10m": 80.0,
        "R@1deg": 20.0,
        "R@2deg": 40.0,
        "R@5deg": 60.0,
        "R@10deg": 80.0,
        "APE": pytest.approx(19.0 / 5),
        "AOE": pytest.approx(42.2 / 5),
        "count": 5,
    }


def test_accumulator_equals_one_shot_evaluation():
    rng = np.random.default_rng(0)
    gt = rng.uniform(-50, 50, size=(10, 3))
    pred = gt + rng.normal(scale=[3.0, 3.0, 0.1], size=(10, 3))
    acc = metrics.MetricAccumulator()
    assert math.isnan(acc.result()["APE"]) and acc.result()["count"] == 0
    acc.update(pred[:4], gt[:4])
    acc.update(pred[4:], gt[4:])
    assert len(acc) == 10
    assert acc.result() == metrics.evaluate_poses(pred, gt)


def test_bad_shapes_are_reported():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        metrics.pose_errors(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(KeyError, match="APE"):
        metrics.table_row("x", {"R@1m": 1.0})


def test_markdown_table_in_paper_layout():
    r = metrics.summarize([0.5, 1.5], [0.5, 20.0])
    table = metrics.markdown_table({"GT seg, SD": r})
    lines = table.splitlines()
    assert lines[0] == (
        "| Method | R@1m | R@2m | R@5m | R@10m | R@1° | R@2° | R@5° | R@10° | APE (m) | AOE (°) |"
    )
    assert lines[1] == "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    assert lines[2] == (
        "| GT seg, SD | 50.00 | 100.00 | 100.00 | 100.00 | 50.00 | 50.00 "
        "| 50.00 | 50.00 | 1.00 | 10.25 |"
    )
    assert metrics.markdown_table([("a", r), ("b", r)]).count("\n") == 3
