"""Shared hypothesis strategies for fuzzing JSON manifests."""

from __future__ import annotations

from hypothesis import strategies as st


def json_values(*extra: str):
    """Any JSON value (NaN and infinities included), nested a few levels; ``extra`` strings
    (file names, mode names) are drawn too, so mutations hit meaningful values."""
    leaves = (st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.integers(-2**70, 2**70)
              | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8))
    if extra:
        leaves = leaves | st.sampled_from(list(extra))
    return st.recursive(leaves, lambda inner: st.lists(inner, max_size=5)
                        | st.dictionaries(st.text(max_size=8), inner, max_size=5), max_leaves=20)


def mutate(doc, path: list, value):
    """Replace the element at ``path`` (indices into nested dicts/lists, taken modulo their size)."""
    if not path or not isinstance(doc, (dict, list)) or not doc:
        return value
    keys = list(doc) if isinstance(doc, dict) else list(range(len(doc)))
    key = keys[path[0] % len(keys)]
    out = dict(doc) if isinstance(doc, dict) else list(doc)
    out[key] = mutate(doc[key], path[1:], value)
    return out
