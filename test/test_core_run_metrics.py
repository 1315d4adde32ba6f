"""cdmp_ros.core.run_metrics: path progress, obstacle drop, tracking error, percentiles,
each against a direct computation."""
import numpy as np
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.run_metrics import (drop_positions, path_progress, percentiles,
                                       point_at_progress, tracking_error)


def test_progress_along_an_l_shaped_path():
    # two legs of length 1 and 3: the corner is at 25 % of the arc length
    path = np.array([[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 1.5, 0], [1, 3, 0]], float)
    assert path_progress(path, [1.0, 0.1, 0.0]) == pytest.approx(0.25)
    assert path_progress(path, [1.1, 2.9, 0.0]) == pytest.approx(1.0)
    np.testing.assert_allclose(point_at_progress(path, 0.25), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(point_at_progress(path, 0.5), [1, 1, 0], atol=1e-12)
    assert path_progress(np.zeros((3, 3)), [1, 1, 1]) == 0.0
    with pytest.raises(ValidationError, match='path'):
        path_progress(np.zeros((4, 2)), [0, 0, 0])
    with pytest.raises(ValueError, match='fraction'):
        point_at_progress(path, 1.5)


def test_drop_is_a_uniformly_accelerated_fall_onto_the_target():
    P = drop_positions([0.3, 0.1, 0.4], 0.5, 11)
    np.testing.assert_allclose(P[0], [0.3, 0.1, 0.9])
    np.testing.assert_allclose(P[-1], [0.3, 0.1, 0.4])
    dz = np.diff(P[:, 2])
    np.testing.assert_allclose(np.diff(dz), dz[1] - dz[0])  # constant second difference
    assert np.all(dz < 0) and np.all(P[:, :2] == [0.3, 0.1])
    with pytest.raises(ValueError, match='height'):
        drop_positions([0, 0, 0], -1.0, 5)


def test_tracking_error_uses_the_latest_reference_before_each_measurement():
    T_ref = np.array([0.0, 1.0, 2.0])
    Q_ref = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, -1.0]])
    T = np.array([-0.5, 0.5, 1.0, 2.5])
    Q = np.array([[9.0, 9.0], [0.1, 0.0], [1.0, 0.3], [2.0, -1.2]])
    e = tracking_error(T_ref, Q_ref, T, Q)
    per_sample = np.array([0.1, 0.3, 0.2])  # the first measurement precedes every reference
    assert e['n'] == 3
    assert e['max_rad'] == pytest.approx(0.3)
    assert e['rms_rad'] == pytest.approx(np.sqrt(np.mean(per_sample ** 2)))
    with pytest.raises(ValidationError, match='Q'):
        tracking_error(T_ref, Q_ref, T, Q[:, :1])


def test_percentiles_match_numpy_and_handle_empty_input():
    x = np.random.default_rng(0).exponential(size=1000)
    p = percentiles(x)
    assert p['p50'] == pytest.approx(np.median(x)) and p['p99'] == pytest.approx(
        np.sort(x)[989] + 0.01 * (np.sort(x)[990] - np.sort(x)[989]))
    assert np.isnan(percentiles([])['p99'])
