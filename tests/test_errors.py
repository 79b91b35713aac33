"""The library's exception types: one base class, and the built-in type each mistake is expected to raise."""

import pytest

from torchrod import errors


@pytest.mark.parametrize(
    ("kind", "builtin"),
    [
        (errors.ReadingError, ValueError),
        (errors.RodError, ValueError),
        (errors.OptionsError, ValueError),
        (errors.MissingFileError, FileNotFoundError),
        (errors.CheckpointError, ValueError),
        (errors.TorchrodTypeError, TypeError),
    ],
)
def test_each_error_is_a_torchrod_error_and_its_builtin(kind, builtin):
    with pytest.raises(errors.TorchrodError):
        raise kind("x")
    with pytest.raises(builtin):
        raise kind("x")
    assert kind.__name__ in errors.__all__ and issubclass(kind, errors.TorchrodError)


def test_rod_warnings_are_torchrod_warnings_and_user_warnings():
    assert issubclass(errors.RodWarning, errors.TorchrodWarning) and issubclass(errors.TorchrodWarning, UserWarning)
    assert {"RodWarning", "TorchrodWarning"} <= set(errors.__all__)


def test_the_library_raises_its_own_errors_where_the_caller_is_wrong():
    """Called as a user would call it, with the mistakes users make: each error is a TorchrodError (and the
    built-in type a Python user expects), and names the fix or the offending value."""
    import numpy as np
    import torch

    import torchrod as tr

    rod = tr.presets.nitinol290()
    est = tr.Estimator(rod, tr.EstimatorOptions(noise=0.1))
    G = rod.num_gratings
    calls = [
        (lambda: est.estimate(np.zeros((1, G, 2))), TypeError, "use torch.as_tensor"),
        (lambda: est.estimate(torch.zeros(1, G, 2, dtype=torch.long)), TypeError, "floating-point"),
        (lambda: est.estimate(torch.zeros(1, G + 1, 2)), ValueError, rf"\(B, {G}, 2\)"),
        (lambda: est.estimate(torch.full((1, G, 2), float("nan"))), ValueError, "no present grating"),
        (lambda: est.estimate(torch.zeros(1, G, 2), torch.ones(1, G)), TypeError, "bool"),
        (lambda: est.estimate(torch.zeros(1, G, 2), options={"noise": 0.1}), TypeError, "EstimatorOptions"),
        (lambda: est.estimate(torch.zeros(1, G, 2), bending_stiffness=-1.0), ValueError, "positive"),
        (lambda: tr.Estimator("nitinol290"), TypeError, "must be a Rod"),
        (lambda: tr.EstimatorOptions(max_forces=-1), ValueError, "max_forces"),
        (lambda: tr.StreamOptions(batch_size=0), ValueError, "batch_size"),
        (lambda: tr.StreamOptions(max_latency=float("nan")), ValueError, "max_latency"),
        (lambda: list(tr.stream(est, [], options={"batch_size": 1})), TypeError, "StreamOptions"),
        (lambda: tr.presets.load("no-such-rod"), ValueError, "no-such-rod"),
        (lambda: tr.simulate(rod, tr.PointForces(torch.tensor([[0.5]]), torch.ones(1, 1, 2))), ValueError, "0.5"),
        (lambda: tr.Rod(length=-1.0, bending_stiffness=1.0, gratings=[0.1]), ValueError, "length"),
        (lambda: tr.WarmStart.load(__file__, rod), ValueError, "not a readable checkpoint"),
        (lambda: tr.rod_shape(rod, "loads"), TypeError, "tensors"),
        (lambda: tr.bending_angle("shape"), TypeError, "Shape"),
        (lambda: tr.calibrate(rod, "data"), TypeError, "CalibrationData"),
    ]
    for call, builtin, match in calls:
        with pytest.raises(errors.TorchrodError, match=match) as caught:
            call()
        assert isinstance(caught.value, builtin), (match, type(caught.value))


def test_training_and_noise_options_raise_options_errors():
    from torchrod.estimate.noise import NoiseLearning
    from torchrod.learn.training import TrainConfig

    with pytest.raises(errors.OptionsError, match="epochs"):
        TrainConfig(epochs=0)
    with pytest.raises(errors.OptionsError, match="window"):
        NoiseLearning(window=2, after=5)
