"""RegisterMap.decode_block's one struct unpacking is pinned to the register-by-register decode
it replaces (protocol.registers._decode_each): the same names in the same order, the same values
of the same types, bit for bit, for any words and any block; words it cannot pack fall back to
it."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from config.loading import default_path, load_toml
from protocol.registers import RegisterMap, _decode_each

RMAP = RegisterMap.load()
_DOC = load_toml(default_path("registers.toml"))
LITTLE = RegisterMap.from_dict({**_DOC, "map": {**_DOC["map"], "word_order": "little"}})
MAPS = {"whole": RMAP, "head 2": RMAP.for_head(2), "head 7": RMAP.for_head(7), "little": LITTLE}


def _same(a: dict, b: dict) -> bool:
    """Equal names in order and values of equal type and bits (NaN payloads too)."""
    if list(a) != list(b):
        return False
    for k in a:
        x, y = a[k], b[k]
        if type(x) is not type(y):
            return False
        if isinstance(x, float):
            if struct.pack(">d", x) != struct.pack(">d", y):
                return False
        elif x != y:
            return False
    return True


@settings(max_examples=300, deadline=None)
@given(
    which=st.sampled_from(sorted(MAPS)),
    start=st.one_of(st.integers(0, 40), st.integers(995, 1260)),
    words=st.lists(st.integers(0, 0xFFFF), min_size=0, max_size=125),
)
def test_decode_block_is_the_register_by_register_decode(which, start, words):
    rmap = MAPS[which]
    assert _same(rmap.decode_block(words, start), _decode_each(rmap, words, start))
    assert _same(rmap.decode_block(tuple(words), start), _decode_each(rmap, words, start))


@given(f=st.floats(width=32, allow_nan=False, allow_infinity=False),
       u=st.integers(0, 2**32 - 1), nan_low=st.integers(1, 0xFFFF))
def test_float32_and_counters_round_trip_through_the_plan(f, u, nan_low):
    words = RMAP.encode_block({"feed_setpoint_mm_s": f, "encoder_counts": u})
    got = RMAP.decode_block(words)
    assert got["feed_setpoint_mm_s"] == f and got["encoder_counts"] == u
    assert _same(got, _decode_each(RMAP, words, 0))
    words[2:4] = [0x7F80, nan_low]  # a NaN with a payload (a PLC answering nonsense)
    assert _same(RMAP.decode_block(words), _decode_each(RMAP, words, 0))


@pytest.mark.parametrize("bad", [[70000], [-1], [1.5]])
def test_words_it_cannot_pack_get_the_register_by_register_checks(bad):
    words = RMAP.encode_block({})
    words[0:1] = bad  # heartbeat_service
    if bad == [1.5]:  # int(1.5): the decode's own conversion
        assert RMAP.decode_block(words)["heartbeat_service"] == 1
        return
    with pytest.raises(ValueError, match="heartbeat_service"):
        RMAP.decode_block(words)


def test_a_map_that_has_decoded_still_pickles_and_decodes_alike():
    """A map goes to a spawned process (the PLC simulator's server) after it may have decoded:
    its decode plans stay behind, the copy builds its own and decodes the same."""
    import copy
    import pickle

    rmap = RegisterMap.load()
    words = rmap.encode_block({"feed_setpoint_mm_s": 12.5})
    head_words = rmap.for_head(1).encode_block({})
    want = rmap.decode_block(words)
    want_head = rmap.for_head(1).decode_block(head_words)
    assert rmap._plans and rmap.for_head(1)._plans  # plans kept on the map and a view
    for twin in (pickle.loads(pickle.dumps(rmap)), copy.deepcopy(rmap)):
        assert _same(twin.decode_block(words), want)
        assert _same(twin.for_head(1).decode_block(head_words), want_head)
    assert rmap._plans  # the original keeps its own


def test_a_head_block_works_out_its_used_words_once_and_still_pickles_and_compares():
    """``HeadBlock.used`` is cached on the block (asked every PLC cycle), equal to the last
    register's last word + 1; the cache changes neither equality, hashing nor pickling."""
    import pickle

    from protocol.registers import RegisterMap

    block = RegisterMap.load().heads
    assert block is not None
    want = max(r.last_address for r in block.registers) + 1
    assert block.used == want and "used" in vars(block)
    assert block.used is block.used
    fresh = RegisterMap.load().heads
    assert fresh == block and hash(fresh) == hash(block)
    back = pickle.loads(pickle.dumps(block))
    assert back == block and back.used == want
