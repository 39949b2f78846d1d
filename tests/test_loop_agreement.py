"""Loop closures checked against a reference (fgslam.evaluation.metrics.loop_agreement, the
count report.json gives for a log with reference poses), and in a simulated run's report."""

from __future__ import annotations

import numpy as np

from fgslam.evaluation.metrics import loop_agreement


def _circle(n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """A robot driving a 10 m circle once in 100 s (times s, poses world)."""
    t = np.linspace(0.0, 100.0, n)
    a = 2 * np.pi * t / 100.0
    return t, np.column_stack([5 * np.cos(a), 5 * np.sin(a), a + np.pi / 2])


def _rel(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    d = b[:2] - a[:2]
    th = np.arctan2(np.sin(b[2] - a[2]), np.cos(b[2] - a[2]))
    return [c * d[0] + s * d[1], -s * d[0] + c * d[1], th]


def test_closures_are_counted_against_the_reference():
    """One closure exact, one 0.5 m off, one 5 deg off, one rejected (not counted), one whose
    keyframe lies after the reference ends (not checked)."""
    t, ref = _circle()
    kf_t = np.array([2.0, 30.0, 50.0, 97.0, 99.0, 150.0])
    kf = np.array([ref[np.argmin(abs(t - x))] if x <= 100 else ref[-1] for x in kf_t])
    from fgslam.evaluation.metrics import interpolate_poses

    true = interpolate_poses(t, ref, kf_t[:5])
    exact = _rel(true[0], true[3])
    off = list(np.add(_rel(true[1], true[4]), [0.5, 0.0, 0.0]))
    turned = list(np.add(_rel(true[0], true[4]), [0.0, 0.0, np.radians(5.0)]))
    closures = [
        {"from": 0, "to": 3, "accepted": True, "pose": exact},
        {"from": 1, "to": 4, "accepted": True, "pose": off},
        {"from": 0, "to": 4, "accepted": True, "pose": turned},
        {"from": 2, "to": 4, "accepted": False, "pose": _rel(true[2], true[4])},
        {"from": 2, "to": 5, "accepted": True, "pose": [0.0, 0.0, 0.0]},
    ]
    out = loop_agreement(closures, kf_t, t, ref)
    assert len(kf) == 6
    assert (out["accepted"], out["checked"], out["agree"]) == (4, 3, 1)
    assert 0.0 <= out["median_error_m"] <= 0.5 + 1e-9
    loose = loop_agreement(closures, kf_t, t, ref, xy_tol=0.6, theta_tol_deg=6.0)
    assert loose["agree"] == 3


def test_no_reference_span_checks_nothing():
    t, ref = _circle()
    out = loop_agreement(
        [{"from": 0, "to": 1, "accepted": True, "pose": [1, 0, 0]}], [200.0, 210.0], t, ref
    )
    assert (out["accepted"], out["checked"], out["agree"]) == (1, 0, 0)
