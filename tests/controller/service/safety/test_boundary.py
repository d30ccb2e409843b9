"""The supervisor boundary (``SafeStateKeeper.boundary``): what it catches and what goes on."""

from __future__ import annotations

import asyncio

import pytest

from controller.service.safe_state import Boundary, Guarded


class _Keeper:
    """Records each fault the boundary reports and answers a status."""

    def __init__(self) -> None:
        self.faults: list[tuple[float, str, BaseException, str]] = []

    def fault(self, t: float, where: str, exc: BaseException, *, part: str) -> str:
        self.faults.append((t, where, exc, part))
        return "safe"


@pytest.mark.parametrize("error", [ValueError("bad"), RuntimeError("x"), KeyError("k"),
                                   ZeroDivisionError()])
def test_an_exception_is_caught_recorded_and_reported(error: Exception) -> None:
    keeper = _Keeper()
    with Boundary(keeper, 1.5, "pair 7", "pair") as g:
        raise error
    assert isinstance(g, Guarded)
    assert g.failed and g.error is error and g.status == "safe"
    assert keeper.faults == [(1.5, "pair 7", error, "pair")]


@pytest.mark.parametrize("error", [asyncio.CancelledError(), KeyboardInterrupt(),
                                   SystemExit(3), GeneratorExit()])
def test_a_base_exception_that_is_not_an_exception_goes_on(error: BaseException) -> None:
    keeper = _Keeper()
    with pytest.raises(type(error)), Boundary(keeper, 0.0, "plc", "plc") as g:
        raise error
    assert not g.failed and g.error is None and g.status is None
    assert keeper.faults == []


def test_a_clean_body_leaves_nothing_and_each_entry_starts_clean() -> None:
    keeper = _Keeper()
    first = Boundary(keeper, 0.0, "can", "can")
    with first as g:
        pass
    assert not g.failed and keeper.faults == []
    with Boundary(keeper, 0.1, "can", "can") as g2:
        raise OSError("bus")
    assert g2.failed and g2 is not g and not g.failed


def test_a_fault_that_raises_carries_the_original_as_its_context() -> None:
    class Broken(_Keeper):
        def fault(self, t, where, exc, *, part):  # noqa: ANN001, ANN201 - a stub
            raise RuntimeError("fault failed")

    with pytest.raises(RuntimeError, match="fault failed") as info, \
            Boundary(Broken(), 0.0, "pair", "pair"):
        raise ValueError("first")
    assert isinstance(info.value.__context__, ValueError)
