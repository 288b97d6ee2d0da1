"""Config fuzz: a few hundred mutations of the shipped quickstart config.

Every mutation either loads or raises a ``FitterError`` with one line naming the
file; nothing else escapes (no KeyError, TypeError, ZeroDivisionError, ...).
Hypothesis draws the mutations from a fixed seed (the suite's "ci" profile is
derandomized), so the run is reproducible.
"""

from __future__ import annotations

import copy
import math
import os
import tomllib

from hypothesis import given, settings
from hypothesis import strategies as st

from fitter.config import dumps_toml, load_config
from fitter.errors import FitterError

QUICKSTART = os.path.join(os.path.dirname(__file__), os.pardir, "configs", "quickstart.toml")
with open(QUICKSTART, "rb") as _fh:
    BASE = tomllib.load(_fh)

SCALARS = st.one_of(
    st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=12), st.sampled_from([0, -1, 1e-300, 1e300, math.nan]))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=4),
                   st.dictionaries(st.text(max_size=6), SCALARS, max_size=2))


def _paths(node, prefix=()):
    """Every (path to a value) in the nested config, tables and arrays of tables included."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield prefix + (key,)
            yield from _paths(value, prefix + (key,))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            if isinstance(value, dict):
                yield from _paths(value, prefix + (i,))


PATHS = sorted(_paths(BASE), key=str)


def _parent(data, path):
    for key in path[:-1]:
        data = data[key]
    return data


@st.composite
def mutated(draw):
    data = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(PATHS))
        try:
            parent = _parent(data, path)
            parent[path[-1]]
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed or replaced it
        action = draw(st.sampled_from(["replace", "delete", "add"]))
        if action == "replace":
            parent[path[-1]] = draw(VALUES)
        elif action == "delete":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = draw(VALUES)
    return data


@settings(max_examples=300)
@given(mutated())
def test_every_mutation_loads_or_is_one_clear_error(tmp_path_factory, data):
    path = str(tmp_path_factory.mktemp("fuzz") / "job.toml")
    try:
        text = dumps_toml(data)
    except TypeError:  # a value TOML cannot hold (e.g. an empty table in an array)
        return
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    try:
        load_config(path)
    except FitterError as exc:
        message = str(exc)
        assert path in message and "\n" not in message, message
