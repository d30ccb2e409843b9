"""Units and counters shared by every layer: wrapping encoder/sequence counters.

The encoder, the trigger latches and the sequence registers are unsigned counters that wrap.
Every place that reads two of them takes their difference here, so the wrap is handled once.
"""

from __future__ import annotations

from core.checks import check_int

__all__ = ["counter_difference", "wrap_counter"]


def wrap_counter(value: int, *, bits: int) -> int:
    """``value`` on an unsigned ``bits``-bit counter, in ``[0, 2**bits)``.

    Parameters
    ----------
    value : int
        Any integer (an unwrapped count).
    bits : int
        Width of the counter, 1..64.
    """
    width = check_int("bits", bits, lo=1, hi=64)
    return int(value) % (1 << width)


def counter_difference(later: int, earlier: int, *, bits: int) -> int:
    """Signed ``later - earlier`` of two readings of a wrapping ``bits``-bit counter.

    The shortest way round: the result lies in ``[-2**(bits-1), 2**(bits-1))``, so a reading
    taken just after the wrap is a small step forward, not a jump back.

    Parameters
    ----------
    later, earlier : int
        Counter readings (any integers; they are taken modulo ``2**bits``).
    bits : int
        Width of the counter, 2..64.

    Returns
    -------
    int
        The signed difference, counts.
    """
    width = check_int("bits", bits, lo=2, hi=64)
    modulus = 1 << width
    half = modulus >> 1
    return (int(later) - int(earlier) + half) % modulus - half
