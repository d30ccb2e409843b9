from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.units import counter_difference, wrap_counter


@given(st.integers(-(2**70), 2**70), st.integers(1, 64))
def test_wrap_is_in_range_and_congruent(value, bits):
    w = wrap_counter(value, bits=bits)
    assert 0 <= w < 2**bits and (w - value) % 2**bits == 0


@given(st.integers(0, 2**40), st.integers(-(2**15) + 1, 2**15 - 1), st.sampled_from([16, 32, 64]))
def test_difference_undoes_a_wrapped_step(start, step, bits):
    """A step smaller than half the counter is recovered exactly across the wrap."""
    a = wrap_counter(start, bits=bits)
    b = wrap_counter(start + step, bits=bits)
    assert counter_difference(b, a, bits=bits) == step
    assert counter_difference(a, b, bits=bits) == -step


@pytest.mark.parametrize(("later", "earlier", "bits", "want"), [
    (5, 65530, 16, 11),          # just after the wrap: forward
    (65530, 5, 16, -11),
    (32768, 0, 16, -32768),      # exactly half: the negative end of the range
    (0, 0, 32, 0),
])
def test_difference_table(later, earlier, bits, want):
    assert counter_difference(later, earlier, bits=bits) == want


@pytest.mark.parametrize("bits", [0, 65, 1.5, "16", True])
def test_bad_width_is_named(bits):
    with pytest.raises(ValueError, match="bits"):
        counter_difference(1, 0, bits=bits)
