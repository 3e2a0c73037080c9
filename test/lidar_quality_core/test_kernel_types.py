"""kernel_types: a kernel typed with array_in takes read-only and writable arrays, one
typed with array_out only writable ones."""
import numpy as np
import pytest
from lidar_quality_core.kernel_types import array_in, array_out
from numba import njit, types


@njit(types.float64(array_in(types.float64, 2)))
def _total(a):
    return a.sum()


@njit(types.void(array_out(types.float64)))
def _zero(a):
    a[:] = 0.0


def test_inputs_take_read_only_and_writable_arrays():
    a = np.ones((2, 3))
    assert _total(a) == 6.0
    a.flags.writeable = False
    assert _total(a) == 6.0


def test_outputs_take_writable_arrays_only():
    a = np.ones(4)
    _zero(a)
    assert not a.any()
    a.flags.writeable = False
    with pytest.raises(TypeError):
        _zero(a)
