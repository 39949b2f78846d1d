"""TUM trajectories read back: exact round trip, and on any input either finite poses or a
ValueError naming the line (hypothesis, bounded)."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fgslam.evaluation import metrics as evaluation

_token = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "1", "-0.0", "1e300", "nan", "inf", "x", "", "#", "1e308"]),
)


@given(st.lists(st.lists(_token, min_size=0, max_size=10), max_size=6))
@settings(max_examples=200, deadline=None)
def test_any_text_gives_finite_poses_or_a_line_error(rows):
    text = "\n".join(" ".join(r) for r in rows) + "\n"
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.tum"
        p.write_text(text)
        try:
            t, poses = evaluation.read_tum(p)
        except ValueError as exc:
            assert str(exc).startswith("line ") and "\n" not in str(exc)
            return
    assert np.isfinite(t).all() and np.isfinite(poses).all()
    assert np.all(np.abs(t) <= evaluation.TUM_MAX_STAMP)


def test_round_trip(tmp_path):
    t = np.array([0.0, 0.5, 1.25])
    poses = np.array([(1.0, -2.0, 0.3), (1.5, -2.0, math.pi - 0.01), (2.0, -1.0, -3.0)])
    evaluation.write_tum(tmp_path / "a.tum", t, poses)
    t2, p2 = evaluation.read_tum(tmp_path / "a.tum")
    assert np.allclose(t2, t) and np.allclose(p2[:, :2], poses[:, :2], atol=1e-6)
    assert np.allclose(evaluation.wrap_angles(p2[:, 2] - poses[:, 2]), 0, atol=1e-8)
