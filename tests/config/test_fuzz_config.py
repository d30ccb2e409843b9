"""Fuzz of the configuration loaders: arbitrary TOML into every loader.

Documents are the shipped files with a few keys replaced by arbitrary TOML values, deleted or
added, plus documents of arbitrary tables and raw text. Every loader either returns its
configuration or raises ``ConfigError`` (a ``ValueError``) whose message names the file and
the key -- never another exception type. Example counts are bounded (a few seconds in CI).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from config.loading import default_path, load_toml
from config.machine import load_machine
from config.rig import load_rig
from config.sim import load_sim
from core.errors import ConfigError
from planer.hil import load_scenario
from protocol.registers import RegisterMap

SCALE = float(os.environ.get("PLANER_FUZZ_SCALE", "1"))
"""Multiplies the example counts: ``PLANER_FUZZ_SCALE=20`` for a deep local run."""
FUZZ = settings(
    max_examples=round(40 * SCALE),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
FUZZ_SMALL = settings(FUZZ, max_examples=round(15 * SCALE))

LOADERS: dict[str, tuple[str, Callable[[Path], Any]]] = {
    "machine": ("machine.toml", load_machine),
    "sim": ("sim.toml", load_sim),
    "rig": ("rig.toml", load_rig),
    "registers": ("registers.toml", RegisterMap.load),
    "scenario": ("hil.toml", lambda p: load_scenario(f"{p}:default")),
}

# ------------------------------------------------------------------ TOML values and documents
scalars = st.one_of(
    st.booleans(),
    st.integers(-(2**63), 2**63 - 1),
    st.sampled_from([0, -1, 1, 2, 7, 65535, 65536, 2**31, 2**32, 10**18]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, 0.5, 1.5, -5.0]),
    st.text(max_size=12),
    st.sampled_from(["", "default", "virtual", "hold", "..", "/etc/hostname", "nan"]),
    st.dates(min_value=dt.date(1, 1, 1)),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5),
        st.dictionaries(st.text(min_size=1, max_size=8), inner, max_size=4),
    ),
    max_leaves=8,
)


def _paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path of a document (tables, keys, entries of arrays of tables)."""
    out = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            if isinstance(v, dict):
                out += _paths(v, (*prefix, i))
    return out


def _parent(doc: Any, path: tuple) -> Any:
    for p in path[:-1]:
        doc = doc[p]
    return doc


@st.composite
def mutated(draw: st.DrawFn, shipped: dict) -> tuple[dict, list[str]]:
    """The shipped document with 1..3 keys replaced, deleted or added; and the touched names."""
    import copy

    doc = copy.deepcopy(shipped)
    touched: list[str] = []
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(doc)
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = _parent(doc, path)
        op = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        names = [str(p) for p in path if isinstance(p, str)]
        if op == "replace":
            parent[path[-1]] = draw(values)
        elif op == "delete":
            del parent[path[-1]]
        else:
            if not isinstance(parent, dict):
                continue
            key = draw(st.text(min_size=1, max_size=8))
            parent[key] = draw(values)
            names.append(key)
        touched += names
    return doc, touched


SHIPPED = {name: load_toml(default_path(file)) for name, (file, _) in LOADERS.items()}


def _load(name: str, text: str | bytes) -> tuple[Path, BaseException | None]:
    folder = Path(tempfile.mkdtemp(prefix="fuzzcfg-"))
    try:
        path = folder / LOADERS[name][0]
        if isinstance(text, bytes):
            path.write_bytes(text)
        else:
            path.write_text(text, encoding="utf-8")
        try:
            LOADERS[name][1](path)
        except ConfigError as exc:
            return path, exc
        except Exception as exc:  # noqa: BLE001 - the test reports the leaked type
            pytest.fail(f"{name} loader leaked {type(exc).__name__}: {exc}\n{text!r}")
        return path, None
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _dump(doc: dict) -> str | None:
    try:
        return tomli_w.dumps(doc)
    except (TypeError, ValueError):  # not representable in TOML (e.g. a list of mixed tables)
        return None


# ------------------------------------------------------------------ the tests
@pytest.mark.parametrize("name", sorted(LOADERS))
def test_shipped_files_load(name):
    text = _dump(SHIPPED[name])
    assert text is not None
    path, exc = _load(name, text)
    assert exc is None, exc


@pytest.mark.parametrize("name", sorted(LOADERS))
@FUZZ
@given(data=st.data())
def test_mutated_shipped_files_load_or_name_the_file_and_the_key(name, data):
    doc, touched = data.draw(mutated(SHIPPED[name]))
    text = _dump(doc)
    if text is None:
        return
    path, exc = _load(name, text)
    if exc is None:
        return
    msg = str(exc)
    assert msg.startswith(f"{path}: ") or f"{path}" in msg, msg  # names the file
    assert "\n" not in msg.strip() or "TOML" in msg
    # names a key of the document: one that was touched, or the one a rule ties it to
    words = set(touched) | _flat_names(doc)
    assert any(w and (w in msg or json.dumps(w) in msg) for w in words), (msg, touched)


def _flat_names(doc: Any) -> set[str]:
    return {str(p) for path in _paths(doc) for p in path if isinstance(p, str)}


@pytest.mark.parametrize("name", sorted(LOADERS))
@FUZZ_SMALL
@given(doc=st.dictionaries(st.text(min_size=1, max_size=8), values, max_size=5))
def test_arbitrary_documents_load_or_name_the_file(name, doc):
    text = _dump(doc)
    if text is None:
        return
    path, exc = _load(name, text)
    if exc is not None:
        assert str(path) in str(exc), str(exc)


@pytest.mark.parametrize("name", sorted(LOADERS))
@FUZZ_SMALL
@given(raw=st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_raw_text_loads_or_names_the_file(name, raw):
    path, exc = _load(name, raw)
    if exc is not None:
        assert str(path) in str(exc), str(exc)


def test_values_are_finite_where_a_number_was_accepted():
    """A NaN or infinite number is never accepted silently by the machine loader."""
    for key in ("timeout_s", "backoff_max_s"):
        doc = {"plc": {key: math.nan}}
        path, exc = _load("machine", tomli_w.dumps(doc))
        assert exc is not None and f"plc.{key}" in str(exc) and str(path) in str(exc)


def test_a_scenarios_sim_config_errors_name_that_file(tmp_path):
    """The simulator file a scenario names is loaded later (``sim_config_for``): still named."""
    from planer.hil.scenario import sim_config_for

    (tmp_path / "bad_sim.toml").write_text("[feed]\nmin_mm_s = -5\n")
    (tmp_path / "scen.toml").write_text('[default]\nsim_config = "bad_sim.toml"\n')
    scenario = load_scenario(str(tmp_path / "scen.toml"))
    with pytest.raises(ConfigError, match=r"bad_sim\.toml: feed\.min_mm_s must be > 0"):
        sim_config_for(scenario)
