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
