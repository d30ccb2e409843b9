"""The text of ``planer bench``'s vision part, from fake result rows (no timing)."""

from __future__ import annotations

import json

import pytest

from planer.commands.bench import _format, vision_row_text, vision_text


def _row(**over: float) -> dict:
    row = {
        "width": 659, "height": 493, "pairs_per_s": 125.0, "copy_pairs_per_s": 30000.0,
        "no_roll_pairs_per_s": 217.0, "selfcal_pairs_per_s": 99.0, "remap_pairs_per_s": 425.0,
        "cpu_ms": 5.62, "selfcal_cpu_ms": 7.03, "remap_cpu_ms": 1.64, "orientation_ms": 2.62,
        "selfcal_ms": 1.41,
    }
    row.update(over)
    return row


def test_row_shows_every_figure_and_the_floor_ratios() -> None:
    row = _row()
    text = vision_row_text(row)
    assert text.startswith("  659x493: 125 pairs/s")
    assert "5.62 ms CPU" in text
    copy_x = row["copy_pairs_per_s"] / row["pairs_per_s"]
    remap_x = row["remap_pairs_per_s"] / row["pairs_per_s"]
    assert f"copy 30000 pairs/s ({copy_x:.0f}x faster)" in text
    assert f"one remap 425 pairs/s, 1.64 ms CPU ({remap_x:.1f}x faster)" in text
    assert "orientation +2.62 ms (without it 217 pairs/s)" in text
    assert "self-calibration +1.41 ms (as the service runs it: 99 pairs/s, 7.03 ms CPU)" in text
    assert len(text.splitlines()) == 3


@pytest.mark.parametrize("rate,floor,want", [(100.0, 250.0, "2.5x"), (10.0, 1234.0, "123x"),
                                             (0.0, 50.0, "?x")])
def test_ratio_follows_the_rates(rate: float, floor: float, want: str) -> None:
    text = vision_row_text(_row(pairs_per_s=rate, remap_pairs_per_s=floor))
    assert f"({want} faster)" in text


def test_negative_step_cost_keeps_its_sign() -> None:
    assert "orientation -0.30 ms" in vision_row_text(_row(orientation_ms=-0.3))


def test_old_rows_without_the_steps_give_one_line_with_the_copy() -> None:
    text = vision_row_text({"width": 1920, "height": 1200, "pairs_per_s": 40.0,
                            "copy_pairs_per_s": 4000.0})
    assert "1920x1200: 40 pairs/s" in text and "copy 4000 pairs/s (100x faster)" in text
    assert "steps" not in text and "remap" not in text


@pytest.mark.parametrize("plain,service,verdicts", [
    (0.447, 0.29, ("OVER", "within")), (0.30, 0.301, ("within", "OVER")),
    (0.12, None, ("within",)),
])
def test_defects_line_judges_each_overhead_against_the_budget(
        plain: float, service: float | None, verdicts: tuple[str, ...]) -> None:
    over = {"defects_ms": 0.64, "defects_overhead": plain}
    if service is not None:
        over.update(service_defects_ms=0.7, service_defects_overhead=service)
    lines = vision_row_text(_row(**over)).splitlines()
    assert len(lines) == 4
    line = lines[-1]
    assert line.startswith("    defects and 2-D map, CPU per pair: +0.64 ms")
    assert f"= {100 * plain:+.0f} % ({verdicts[0]} the +30 % budget)" in line
    assert ("on the service's measurement +0.70 ms" in line) == (service is not None)
    if service is not None:
        assert line.endswith(f"= {100 * service:+.0f} % ({verdicts[1]} the +30 % budget)")


def test_part_text_has_one_block_per_size() -> None:
    rows = [_row(), _row(width=1920, height=1200, pairs_per_s=42.0)]
    text = vision_text(rows)
    assert text.splitlines()[0] == "vision (one core):"
    assert sum(line.startswith("  ") and "pairs/s," in line and "x" in line.split(":")[0]
               for line in text.splitlines()) == 2
    assert _format("vision", rows) == text


def test_unknown_shape_falls_back_to_json() -> None:
    bad = [{"width": 1}]
    assert _format("vision", bad) == f"vision: {json.dumps(bad, indent=2)}"


def test_a_bare_bench_runs_the_quality_log_and_formats_it() -> None:
    from planer.commands.bench import DEFAULT_PARTS

    assert "quality_log" in DEFAULT_PARTS
    result = {"heads": 4, "rate_hz_per_head": 100.0, "records": 1200, "all_logged": True,
              "cpu_ms_per_record": 0.339, "records_per_cpu_s": 2953.0, "user_ms_per_record": 0.292,
              "system_ms_per_record": 0.092, "records_per_append": 4.0,
              "records_per_transaction": 22.6, "shared_writer": True}
    text = _format("quality_log", result)
    assert "one writer group" in text
    assert "0.339 ms a record" in text
    assert "2953 records per CPU-second" in text
    assert "4.0 records an fsync'ed journal append, 22.6 a transaction" in text
