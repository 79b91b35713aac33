"""The shared reading checks: missing gratings are masked, bad shapes and inconsistent masks are named."""

import math

import pytest
import torch

from torchrod.io.readings import check_readings


def test_nan_gratings_are_masked_not_zeroed():
    u = torch.ones(2, 3, 2, dtype=torch.float64)
    u[1, 2] = math.nan
    out, mask = check_readings(u, None, 3)
    assert out is u  # values are not rewritten
    assert mask.tolist() == [[True, True, True], [True, True, False]]


@pytest.mark.parametrize("shape", [(2, 4, 2), (2, 3), (2, 3, 3)])
def test_wrong_shapes_name_the_shape(shape):
    with pytest.raises(ValueError, match=r"\(B, 3, 2\)"):
        check_readings(torch.zeros(shape), None, 3)


def test_mask_checks():
    u = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match="mask must have shape"):
        check_readings(u, torch.ones(2, 4, dtype=torch.bool), 3)
    with pytest.raises(TypeError, match="bool"):
        check_readings(u, torch.ones(2, 3), 3)
    u[0, 1, 0] = math.nan
    with pytest.raises(ValueError, match=r"curvature\[0, 1\] is not finite"):
        check_readings(u, torch.ones(2, 3, dtype=torch.bool), 3)
    with pytest.raises(TypeError, match="floating-point"):
        check_readings(torch.zeros(2, 3, 2, dtype=torch.long), None, 3)
