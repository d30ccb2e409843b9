"""``planer serve``'s lines: the frame source's counters and the vision's state."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from planer.commands.serve import source_counts, source_text


@pytest.mark.parametrize(
    "source, expected",
    [
        # a camera source: the pairing's counters and Aravis' own
        (SimpleNamespace(counters={"images": 1200, "pairs": 598, "failed": 2, "dropped": 3,
                                   "skipped_images": 1, "latches": 600, "queue_dropped": 4,
                                   "aravis_n_failures": 0}),
         {"images": 1200, "pairs": 598, "failed": 2, "dropped": 7}),
        (SimpleNamespace(counters={"images": 10, "pairs": 5}), {"images": 10, "pairs": 5}),
        # a spool source: pairs handed over, pairs given up
        (SimpleNamespace(received=41, abandoned=1, restarts=0), {"pairs": 41, "dropped": 1}),
        # an in-process queue: pairs handed over, dropped from a full queue
        (SimpleNamespace(received=9, dropped=2), {"pairs": 9, "dropped": 2}),
        (SimpleNamespace(), {}),
        (SimpleNamespace(received=True, counters=None), {}),  # nothing countable
    ],
)
def test_source_counts_of_every_kind_of_source(source, expected):
    counts = source_counts(source)
    assert counts == expected
    text = source_text(counts)
    if expected:
        assert text.startswith("source: ")
        assert all(f"{k} {v}" in text for k, v in expected.items())
    else:
        assert text == ""



@pytest.mark.parametrize(
    "meas, parts",
    [
        (SimpleNamespace(roll_deg=0.4172, calibration=SimpleNamespace(
            gain=0.8971, trusted=True, gain_confidence=0.9, scatter_mm=0.1,
            scatter_fraction=0.5, scatter_confidence=0.8)),
         ["roll +0.42 deg", "calibration applied (gain 0.897)"]),
        (SimpleNamespace(roll_deg=-1.0, calibration=SimpleNamespace(gain=1.3, trusted=False)),
         ["roll -1.00 deg", "calibration untrusted (gain 1.300)"]),
        (SimpleNamespace(roll_deg=0.0, calibration=None), ["roll +0.00 deg", "calibration off"]),
        (SimpleNamespace(pitch_mm=1.5), []),  # a measurer without orientation or calibration
        (None, []),
    ],
)
def test_progress_line_says_the_roll_and_the_calibration(meas, parts):
    from planer.commands.serve import vision_text

    assert vision_text(meas) == ", ".join(parts)
