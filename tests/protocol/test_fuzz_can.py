"""Fuzz of the piezo CAN decoder: arbitrary ids, data and lengths.

Whatever arrives on the bus, :meth:`PiezoCodec.decode` either returns a message of the DBC file
with every signal inside its declared range, or raises ``ValueError`` naming the id or the
message -- never another exception type. Example counts are bounded (a few seconds in CI).
"""

from __future__ import annotations

import math
import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol.piezo_can import PiezoCodec

CODEC = PiezoCodec.load()
MESSAGES = {m.frame_id: m for m in CODEC._db.messages}  # noqa: SLF001 - the DBC's own view
KNOWN_IDS = sorted(MESSAGES)

SCALE = float(os.environ.get("PLANER_FUZZ_SCALE", "1"))
"""Multiplies the example counts: ``PLANER_FUZZ_SCALE=20`` for a deep local run."""
FUZZ = settings(
    max_examples=round(150 * SCALE),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

can_ids = st.one_of(
    st.sampled_from(KNOWN_IDS),
    st.integers(0, 0x7FF),  # standard ids
    st.integers(0, 0x1FFF_FFFF),  # extended ids
    st.integers(-(2**40), 2**40),  # what no bus carries
)
payloads = st.binary(min_size=0, max_size=64)  # CAN FD carries up to 64 bytes


def _check_decoded(fid: int, data: bytes, name: str, signals: dict) -> None:
    msg = MESSAGES[fid]
    assert name == msg.name and len(data) >= msg.length
    assert set(signals) == {s.name for s in msg.signals}
    for sig in msg.signals:
        v = signals[sig.name]
        assert isinstance(v, (int, float)) and math.isfinite(v)
        # a decoded value lies in the raw field's physical range (the DBC min/max may be
        # narrower: the decoder reports what came, the caller judges it)
        raw_bits = sig.length
        lo_raw = -(2 ** (raw_bits - 1)) if sig.is_signed else 0
        hi_raw = 2 ** (raw_bits - 1) - 1 if sig.is_signed else 2**raw_bits - 1
        ends = sorted((lo_raw * sig.scale + sig.offset, hi_raw * sig.scale + sig.offset))
        tol = abs(sig.scale)
        assert ends[0] - tol <= v <= ends[1] + tol, (sig.name, v)


@FUZZ
@given(can_ids, payloads)
def test_decode_arbitrary_frames_returns_a_dbc_message_or_a_value_error(fid, data):
    try:
        name, signals = CODEC.decode(fid, data)
    except ValueError as exc:
        text = str(exc)
        assert text  # says what is wrong
        if fid in MESSAGES:
            assert MESSAGES[fid].name in text  # names the message it tried to decode
        else:
            assert f"0x{fid:X}" in text or "arbitration id" in text
        return
    _check_decoded(fid, data, name, signals)


@FUZZ
@given(st.sampled_from(KNOWN_IDS), payloads)
def test_known_ids_decode_whenever_the_frame_is_long_enough(fid, data):
    msg = MESSAGES[fid]
    if len(data) < msg.length:
        with pytest.raises(ValueError, match=msg.name):
            CODEC.decode(fid, data)
        return
    name, signals = CODEC.decode(fid, data)
    _check_decoded(fid, data, name, signals)
    # extra bytes beyond the message's length are ignored
    assert CODEC.decode(fid, data[: msg.length]) == (name, signals)


@FUZZ
@given(st.sampled_from(KNOWN_IDS), st.binary(min_size=8, max_size=8))
def test_decoded_frames_encode_back_to_the_same_signals(fid, data):
    """Decode then encode is stable: what the decoder reports is what the frame carries."""
    msg = MESSAGES[fid]
    name, signals = CODEC.decode(fid, data)
    in_range = all(
        sig.minimum is None or sig.minimum - abs(sig.scale) <= signals[sig.name] <= sig.maximum
        + abs(sig.scale)
        for sig in msg.signals
    )
    if not in_range:
        return  # the encoder refuses values outside the DBC range on purpose
    again = msg.encode(dict(signals), scaling=True, strict=False)
    assert CODEC.decode(fid, again) == (name, signals)


@FUZZ
@given(st.one_of(st.none(), st.text(max_size=5), st.floats(), st.lists(st.integers(), max_size=3)),
       payloads)
def test_ids_that_are_not_integers_are_value_errors(fid, data):
    with pytest.raises((ValueError, TypeError)) as err:
        CODEC.decode(fid, data)  # type: ignore[arg-type]
    assert err.type is ValueError, f"{err.type.__name__}: {err.value}"


@FUZZ
@given(st.sampled_from(KNOWN_IDS),
       st.one_of(st.none(), st.text(max_size=8), st.lists(st.integers(-300, 300), max_size=9)))
def test_data_that_is_not_bytes_is_a_value_error(fid, data):
    with pytest.raises(Exception) as err:  # noqa: B017 - the assertion names what leaked
        CODEC.decode(fid, data)  # type: ignore[arg-type]
    assert err.type is ValueError, f"{err.type.__name__} leaked: {err.value}"
    assert "bytes" in str(err.value)


# ------------------------------------------------------------------ the DBC file itself
def _dbc_lines() -> list[str]:
    from config.loading import default_path

    return default_path("piezo.dbc").read_text().splitlines()


SG_TOKENS = [
    "0|1@1+", "8|4@1+", "0|16@1-", "60|16@1-", "0|64@1+", "7|8@0+", "0|0@1+",
    "(1,0)", "(0,0)", "(0.001,0)", "(-1,5)", "(1e-12,0)", "(1e300,0)",
    "[0|1]", "[1|0]", "[0|0]", "[-32.768|32.767]", "[|]", "[0|1e400]",
    '"um"', '""', "AMP", "SERVICE", ":",
]


@st.composite
def mutated_dbc(draw: st.DrawFn) -> str:
    lines = _dbc_lines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["token", "token", "token", "delete", "duplicate"]))
        if op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        else:
            words = lines[i].split(" ")
            j = draw(st.integers(0, len(words) - 1))
            words[j] = draw(st.sampled_from(SG_TOKENS))
            lines[i] = " ".join(words)
    return "\n".join(lines) + "\n"


def _use(codec: PiezoCodec, data: bytes) -> None:
    """Everything the service and the simulator do with a codec; only ValueError may leave."""
    calls = [
        lambda: codec.encode_command(enable=True, knives=4, alive_counter=1),
        lambda: codec.encode_offsets([0.0, 1.5, -2.0, 0.25, 3.0]),
        lambda: codec.encode_status(displacement_um=1.0, temperature_c=30.0, fault=0, state=1,
                                    alive_counter=2),
        lambda: codec.encode_heartbeat(),
    ]
    frames = []
    for call in calls:
        try:
            out = call()
        except ValueError:
            continue
        frames += out if isinstance(out, list) else [out]
    for fid, payload in frames:
        codec.decode(fid, payload)
    for fid in codec.ids.values():
        try:
            codec.decode(fid, data)
        except ValueError:
            pass


@settings(FUZZ, max_examples=round(60 * SCALE))
@given(mutated_dbc(), st.binary(min_size=8, max_size=8))
def test_mutated_dbc_files_load_or_name_the_file_and_then_only_refuse_with_value_errors(
    text, data
):
    import tempfile
    from pathlib import Path

    from core.errors import ConfigError

    with tempfile.TemporaryDirectory(prefix="fuzzdbc-") as folder:
        path = Path(folder) / "piezo.dbc"
        path.write_text(text)
        try:
            codec = PiezoCodec.load(path)
        except ConfigError as exc:
            assert str(path) in str(exc), str(exc)
            return
        except Exception as exc:  # noqa: BLE001 - the assertion names what leaked
            pytest.fail(f"load leaked {type(exc).__name__}: {exc}\n{text}")
    try:
        _use(codec, data)
    except ValueError:
        pass
    except Exception as exc:  # noqa: BLE001 - the assertion names what leaked
        pytest.fail(f"a loaded codec leaked {type(exc).__name__}: {exc}\n{text}")
