"""Per-trial numbers of every filter equal the recorded reference (tests/reference/per_trial.json).

The reference was recorded with per-trial random streams; a refactoring that is not meant to change
the numbers (the flow-layer redesign) must reproduce it trial by trial. Tolerance: 1e-9 relative,
room for BLAS round-off only (a changed random draw or formula moves the numbers by far more).
"""
import json
import math

import pytest

from tests.reference import cases as reference

RECORDED = json.loads((reference.HERE / "per_trial.json").read_text())["cases"]


@pytest.mark.parametrize("name", sorted(RECORDED))
def test_per_trial_numbers_match_the_reference(name):
    model, filters, kw = reference.cases()[name]
    got = reference.run_case(model, filters, kw)
    want = RECORDED[name]
    assert [(r["filter"], r["trial"]) for r in got] == [(r["filter"], r["trial"]) for r in want]
    bad = []
    for g, w in zip(got, want):
        assert set(g) == set(w), (g, w)
        for k, v in w.items():
            if isinstance(v, float) and not math.isclose(g[k], v, rel_tol=1e-9, abs_tol=1e-12):
                bad.append(f"{g['filter']} trial {g['trial']} {k}: {g[k]!r} != {v!r}")
            elif not isinstance(v, float) and g[k] != v:
                bad.append(f"{g['filter']} trial {g['trial']} {k}: {g[k]!r} != {v!r}")
    assert not bad, "\n".join(bad[:20])
