"""Fuzz of the spool's edge decoders: pair metadata, PNG and .npy headers, image decoding.

No input crashes or hangs them; every refusal is the one documented error with a clear text.
Example counts are bounded (a few seconds in CI, derandomised there: tests/conftest.py).
"""

from __future__ import annotations

import io
import json
import math

import cv2
import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from core.errors import MeasurementError
from core.imageio import ImageHeader, npy_header, png_header
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter
from protocol.spool_files import (
    MetadataRefused,
    PairMetadata,
    SpoolFileError,
    SpoolLimits,
    decode_metadata,
    decode_spool_image,
)

FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True)
    | st.text(max_size=20),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids,
                                                              max_size=4),
    max_leaves=12,
)
_FIELDS = ("seq", "t_s", "counts_a", "counts_b", "speed_mm_s", "index_latch_counts",
           "board_id", "board_position_mm", "truth", "image_a", "image_b", "version", "slot")


def _check_metadata(meta: PairMetadata) -> None:
    f = meta.fields
    for name in ("seq", "counts_a", "counts_b", "index_latch_counts", "board_id"):
        assert isinstance(f[name], int) and not isinstance(f[name], bool)
        assert abs(f[name]) < 2**63
    assert f["seq"] >= 0 and f["board_id"] >= 0
    for name in ("t_s", "speed_mm_s", "board_position_mm"):
        assert isinstance(f[name], float) and math.isfinite(f[name])
    assert f["truth"] is None or isinstance(f["truth"], dict)
    for p in meta.problems:
        assert isinstance(p, str) and p and "\n" not in p
    Frame(image_a=None, image_b=None, **f)  # always makes a frame


@FUZZ
@given(st.binary(max_size=300))
def test_metadata_decoder_on_any_bytes(data):
    try:
        meta = decode_metadata(data, slot=0)
    except MetadataRefused as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    _check_metadata(meta)


@FUZZ
@given(st.dictionaries(st.sampled_from(_FIELDS), _json_values, max_size=len(_FIELDS)),
       st.integers(0, 10**12))
def test_metadata_decoder_names_each_invalid_field(doc, slot):
    data = json.dumps(doc).encode()
    try:
        meta = decode_metadata(data, slot=slot)
    except MetadataRefused as exc:
        seq = doc.get("seq")
        assert ("seq" not in doc or isinstance(seq, bool) or not isinstance(seq, int)
                or ("slot" in doc and (isinstance(doc["slot"], bool)
                                       or doc["slot"] != slot))), exc
        return
    _check_metadata(meta)
    text = " ".join(meta.problems)
    for name in ("seq", "counts_a", "counts_b", "index_latch_counts", "board_id"):
        if name in doc and doc[name] != meta.fields[name]:
            assert name in text  # replaced only when refused, and then named
    if not meta.problems:
        assert meta.seq_ok and meta.fields["seq"] == doc["seq"]


def _png_bytes(shape=(6, 9), dtype=np.uint8) -> bytes:
    img = (np.arange(shape[0] * shape[1]).reshape(shape) % 250).astype(dtype)
    return cv2.imencode(".png", img)[1].tobytes()


_GOOD = {"u8": _png_bytes(), "u16": _png_bytes(dtype=np.uint16)}


@st.composite
def _mutated_png(draw) -> bytes:
    data = bytearray(_GOOD[draw(st.sampled_from(sorted(_GOOD)))])
    for _ in range(draw(st.integers(0, 4))):
        i = draw(st.integers(0, len(data) - 1))
        data[i] = draw(st.integers(0, 255))
    cut = draw(st.integers(0, len(data)))
    if draw(st.booleans()):
        data = data[:cut]
    return bytes(data)


LIMITS = SpoolLimits(max_pixels=64 * 64)


@FUZZ
@given(st.one_of(_mutated_png(), st.binary(max_size=200)))
def test_png_header_and_decoding_never_crash(data):
    try:
        head = png_header(data)
    except MeasurementError as exc:
        assert str(exc) and "\n" not in str(exc)
    else:
        assert isinstance(head, ImageHeader) and head.width >= 1 and head.height >= 1
    try:
        img = decode_spool_image(data, "pair-000000000000.a.png", limits=LIMITS)
    except SpoolFileError as exc:
        assert str(exc) and "\n" not in str(exc)
    else:
        assert img.ndim == 2 and img.size <= LIMITS.max_pixels


def _npy_bytes() -> bytes:
    bio = io.BytesIO()
    np.save(bio, np.ones((4, 5), np.float32))
    return bio.getvalue()


@FUZZ
@given(st.binary(max_size=200), st.lists(st.tuples(st.integers(0, 200), st.integers(0, 255)),
                                        max_size=4), st.integers(0, 300))
@example(noise=b"", flips=[(10, 0)], cut=128)  # once raised tokenize.TokenError from numpy
def test_npy_header_and_decoding_never_crash(noise, flips, cut):
    for base in (noise, _npy_bytes()):
        data = bytearray(base)
        for i, v in flips:
            if i < len(data):
                data[i] = v
        data = bytes(data[:cut])
        try:
            npy_header(data)
        except MeasurementError as exc:
            assert str(exc)
        try:
            img = decode_spool_image(data, "pair-000000000000.a.npy", limits=LIMITS)
        except SpoolFileError as exc:
            assert str(exc)
        else:
            assert img.ndim == 2


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=120), _mutated_png())
def test_reader_survives_any_metadata_and_image(tmp_path_factory, meta_bytes, png):
    d = tmp_path_factory.mktemp("spool")
    w = SpoolWriter(d, fsync=False)
    img = np.zeros((6, 9), np.uint8)
    for s in (1, 2, 3):
        w.write(Frame(seq=s, t_s=float(s), image_a=img, image_b=img, counts_a=s, counts_b=s,
                      speed_mm_s=1.0))
    (d / "pair-000000000001.json").write_bytes(meta_bytes)
    (d / "pair-000000000002.a.png").write_bytes(png)
    r = SpoolReader(d, start="all", limits=LIMITS)
    got = []
    while (f := r.poll()) is not None:
        got.append(f)
    skips = r.take_skips()
    assert len(got) + len(skips) == 3  # every pair: a frame or a reported skip
    assert got[0].seq == 1 and got[0].error is None
