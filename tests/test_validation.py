"""Bad input fails early with a message naming the argument and the expected shape."""

import numpy as np
import pytest

import jdrkf


F, H, Q, R = np.eye(2), np.ones((1, 2)), np.eye(2), np.eye(1)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(H=np.ones((2, 3))), r"H has shape \(2, 3\) but expected trailing shape \(2, 2\) since the state dimension is 2"),
        (dict(F=np.ones((2, 3))), r"F has shape \(2, 3\)"),
        (dict(Q=np.ones((2, 3))), "Q must be square"),
        (dict(R=np.array([[1.0, 0.2], [0.0, 1.0]]), H=np.ones((2, 2))), "R must be symmetric"),
        (dict(R=np.eye(2)), r"R has shape \(2, 2\) but expected trailing shape \(1, 1\) since H has 1 rows"),
        (dict(Q=-np.eye(2)), "Q must be positive semidefinite"),
        (dict(Q=np.eye(3)), r"pass G of shape \(2, 3\)"),
        (dict(G=np.ones((3, 2))), r"G has shape \(3, 2\)"),
        (dict(process_mean=np.zeros(3)), "process_mean has shape"),
        (dict(noise_mean=np.zeros(2)), "noise_mean has shape"),
        (dict(F=np.stack([np.eye(2)] * 5), R=np.stack([np.eye(1)] * 4)), "time axis of length 4 but other time-varying fields have length 5"),
        (dict(F=np.ones((2, 2, 2, 2))), "F must have 2 or 3 dimensions"),
        (dict(F=np.array([["a", "b"], ["c", "d"]])), "F must be a numeric array, got ndarray of dtype <U1"),
    ],
)
def test_model_validation(kwargs, match):
    args = dict(F=F, H=H, Q=Q, R=R) | kwargs
    with pytest.raises(ValueError, match=match):
        jdrkf.LinearModel(**args)


def test_integer_inputs_are_promoted():
    model = jdrkf.LinearModel(np.eye(2, dtype=int), np.ones((1, 2), dtype=int), np.eye(2), np.eye(1))
    assert model.F.dtype == model.Q.dtype


def test_filter_call_validation():
    model, prior = jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(np.zeros(2), np.eye(2))
    kf = jdrkf.KalmanFilter()
    with pytest.raises(ValueError, match=r"ys has shape \(10, 2\) but expected \(T, 1\)"):
        kf(model, prior, np.zeros((10, 2)))
    with pytest.raises(ValueError, match="ys must have 2 dimensions"):
        kf(model, prior, np.zeros(10))
    with pytest.raises(ValueError, match="prior has dimension 3 but the state dimension is 2"):
        kf(model, jdrkf.Gaussian(np.zeros(3), np.eye(3)), np.zeros((10, 1)))
    with pytest.raises(ValueError, match="model must be a jdrkf.LinearModel"):
        kf("model", prior, np.zeros((10, 1)))
    with pytest.raises(ValueError, match="no control matrix B"):
        kf(model, prior, np.zeros((10, 1)), inputs=np.zeros((10, 1)))
    tv = jdrkf.LinearModel(np.stack([F] * 5), H, Q, R)
    with pytest.raises(ValueError, match="time-varying with 5 steps but 10 steps"):
        kf(tv, prior, np.zeros((10, 1)))
    controlled = jdrkf.LinearModel(F, H, Q, R, B=np.ones((2, 3)))
    with pytest.raises(ValueError, match="no inputs were given"):
        kf(controlled, prior, np.zeros((10, 1)))
    with pytest.raises(ValueError, match=r"inputs has shape \(10, 2\) but expected \(10, 3\)"):
        kf(controlled, prior, np.zeros((10, 1)), inputs=np.zeros((10, 2)))


def test_simulate_requires_key():
    model, prior = jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="PRNG key"):
        jdrkf.simulate(None, model, prior, 10, 2)
