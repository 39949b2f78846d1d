"""The laser's range offset and scale as estimated calibration errors (issue 15, section 1):
recovered from a simulated run with a known range bias, by every backend, and the
trajectory better than with the paper's worst-case term."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fgslam.config import ConfigError, from_dict, load_config, with_options, with_scanmatch
from fgslam.evaluation import metrics as evaluation
from fgslam.sim.scenes import PAPER, ROOM
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import parse_world
from fgslam.slam.calibration import Calibration
from fgslam.slam.runner import run_backends

BACKENDS = ["ekf", "isam2", "batch"]


def _biased_room(offset: float, scale: float, wheels=(0.0, 0.0, 0.0)):
    """The room driven with the laser's ranges read r (1 + scale) + offset and the wheels'
    relative errors ``wheels`` (right, left, wheelbase; sonar without its per-run
    sound-speed bias)."""
    cfg = load_config()
    w = parse_world(ROOM, "room")
    p = SimParams(
        radius_error_right=wheels[0],
        radius_error_left=wheels[1],
        wheelbase_error=wheels[2],
        laser_sys_offset=offset,
        laser_sys_per_metre=scale,
        sound_speed_bias_sigma=0,
    )
    return list(events(w, cfg, plan_run(w, cfg, 2, p), p)), cfg


def _run(evs, cfg, calibration: str, prior: tuple[float, float], backends=BACKENDS, wheels="off"):
    cfg = with_scanmatch(cfg, PAPER)
    las = dataclasses.replace(
        cfg.laser,
        calibration=calibration,
        systematic_offset=prior[0],
        systematic_per_metre=prior[1],
    )
    cfg = dataclasses.replace(
        cfg, laser=las, odometry=dataclasses.replace(cfg.odometry, calibration=wheels)
    )
    out = {}
    for res in run_backends(evs, cfg, backends, "fused"):
        ref = evaluation.interpolate_poses(res.truth_t, res.truth, res.times)
        out[res.backend] = (res, evaluation.ate(res.poses, ref, align=False)["rmse"])
    return out


def _check_recovery(truth, prior, backends, within_sigma: bool | None):
    """``within_sigma``: the estimate within 3 sigma (True), a quarter of the truth (False),
    or not checked (None)."""
    evs, cfg = _biased_room(*truth)
    off = _run(evs, cfg, "off", prior, backends)
    on = _run(evs, cfg, "range", prior, backends)
    for b in backends:
        res, ate = on[b]
        assert off[b][0].calibration is None
        assert res.calibration["parameters"] == ["laser_offset", "laser_scale"]
        est, sig = np.array(res.calibration["estimate"]), np.array(res.calibration["sigma"])
        if within_sigma:
            assert np.all(np.abs(est - truth) < 3 * sig), (b, est, sig)
        elif within_sigma is False:
            assert np.all(np.abs(est - truth) < 0.25 * np.abs(truth)), (b, est)
        assert np.all(sig < np.array(prior) / 4), (b, sig)
        assert ate < 0.9 * off[b][1], (b, ate, off[b][1])


def test_every_backend_recovers_a_known_range_bias():
    """The simulator's default laser (8 mm + 0.15 %), estimated with the configured
    systematic bounds as prior sigmas: the graph's offset and scale within 3 sigma of the
    truth; every backend's sigmas learned from the data (a quarter of the prior or less) and
    its trajectory more accurate than with the worst-case term. The EKF's estimate is not
    asserted: the room's ranges tell offset and scale apart only weakly, and the filter,
    which cannot relinearise, lands along that direction (measured: -0.1 mm and 5.7e-3, 15
    and 9 sigma off; 6.6 mm and 1.4e-3 when the simulator drew mixed pixels on walls seen at
    grazing angles too)."""
    _check_recovery((0.008, 0.0015), (0.01, 0.002), ["isam2", "batch"], within_sigma=True)
    _check_recovery((0.008, 0.0015), (0.01, 0.002), ["ekf"], within_sigma=None)


def test_a_larger_range_bias_is_recovered_to_a_quarter():
    """A 2 cm + 0.5 % bias, iSAM2 and batch: within a quarter of the truth (measured: offset
    1.69 cm, 2.8 sigma short; scale 0.50 %), the trajectory more accurate than with the
    worst-case term. The EKF, which cannot relinearise, overshoots by 21 % and 37 %
    (2.42 cm, 0.69 %; 5 and 4 sigma): not asserted."""
    _check_recovery((0.02, 0.005), (0.03, 0.01), ["isam2", "batch"], within_sigma=False)


def test_wheels_and_laser_offset_recovered_together():
    """Wheels 2 %, -1.5 %, 2.5 % off and a 1 cm range offset, estimated together (the
    scale, which only the wheels' scale could tell apart, left out), iSAM2 and batch: the
    wheels within 3 sigma of the truth, the offset within 5 mm of it. Measured: 1.35 cm,
    4.9 sigma over, as the front end's lines are measured 2-5 mm too far on average in
    this room (experiments/README.md, laser_calibration.py); the EKF likewise."""
    truth = np.array([0.02, -0.015, 0.025, 0.01])
    evs, cfg = _biased_room(0.01, 0.0, tuple(truth[:3]))
    cfg = dataclasses.replace(
        cfg, odometry=dataclasses.replace(cfg.odometry, calibration_sigma=(0.05,) * 3)
    )
    runs = _run(evs, cfg, "offset", (0.03, 0.002), ["isam2", "batch"], wheels="wheels")
    for b, (res, _) in runs.items():
        assert res.calibration["parameters"] == ["e_r", "e_l", "e_b", "laser_offset"]
        est, sig = np.array(res.calibration["estimate"]), np.array(res.calibration["sigma"])
        assert np.all(np.abs(est - truth)[:3] < 3 * sig[:3]), (b, est, sig)
        assert abs(est[3] - truth[3]) < 0.005, (b, est)
        assert sig[3] < 0.03 / 4, (b, sig)


def test_wheels_and_laser_in_one_calibration_vector():
    """Both parts: one prior, block diagonal, the wheels first; Jacobians embedded in their
    columns; a feature without laser range (sonar) involves none of c."""
    cal = Calibration.of(np.eye(3) * 1e-4, np.diag([1e-4, 4e-6]))
    assert cal.names == ("e_r", "e_l", "e_b", "laser_offset", "laser_scale")
    assert cal.wheels == slice(0, 3) and cal.laser == slice(3, 5)
    np.testing.assert_allclose(np.diag(cal.prior), [1e-4] * 4 + [4e-6])
    J = cal.measurement_jacobian(np.array([[1.0, 2.0], [3.0, 4.0]]))
    np.testing.assert_allclose(J, [[0, 0, 0, 1, 2], [0, 0, 0, 3, 4]])
    assert cal.measurement_jacobian(None) is None
    only_laser = Calibration.of(laser=np.eye(2))
    assert only_laser.wheels is None and only_laser.laser == slice(0, 2)
    with pytest.raises(ValueError):
        only_laser.wheel_jacobian(np.eye(3))
    assert Calibration.of() is None
    offset = Calibration.of(np.eye(3), np.array([[1e-4]]))
    assert offset.names == ("e_r", "e_l", "e_b", "laser_offset")
    np.testing.assert_allclose(offset.measurement_jacobian(np.array([[1.0, 2.0]])), [[0, 0, 0, 1]])


def test_range_calibration_needs_positive_priors():
    data = load_config().to_dict()
    data["laser"] = {**data["laser"], "calibration": "range", "systematic_offset": 0.0}
    with pytest.raises(ConfigError, match=r"laser\.calibration"):
        from_dict(data)
    data["laser"].update(systematic_offset=0.01, systematic_per_metre=0.0)
    with pytest.raises(ConfigError, match=r"laser\.calibration"):
        from_dict(data)
    data["laser"]["calibration"] = "offset"  # the scale keeps its (zero) worst case
    assert from_dict(data).laser.calibration_prior().shape == (1, 1)
    data["laser"]["calibration"] = "meters"
    with pytest.raises(ConfigError, match=r"laser\.calibration"):
        from_dict(data)


def test_a_free_range_scale_is_not_pulled_off():
    """The simulated corridor with a laser free of systematic errors, its offset and scale
    estimated with the wheels' errors (laser only, iSAM2, the whole run), the lines ending at
    their vertices (``[frontend] line_ends = "at-vertex"``): the scale stays within 4 sigma
    of its true zero and under 5e-3, the wheels within 4 sigma of theirs (measured: the
    scale +4.3e-3, 3.4 sigma, the wheels 3.5 sigma under: a pull is left). Before the
    scale's Jacobian was taken at the prediction it settled at +8e-3 (+13e-3, 10 sigma, with
    the lines as segmented too; the wheels 13e-3 under theirs: the map 1.4 % too small)."""
    from fgslam.sim.world import load_world

    cfg = load_config()
    p = SimParams(laser_sys_offset=0.0, laser_sys_per_metre=0.0, mixed_pixel_prob=0.0)
    w = load_world("corridor")
    evs = list(events(w, cfg, plan_run(w, cfg, 0, p), p))
    cfg = with_scanmatch(cfg, PAPER)
    cfg = with_options(
        cfg, {"laser": {"calibration": "range"}, "frontend": {"line_ends": "at-vertex"}}
    )
    (res,) = run_backends(evs, cfg, ["isam2"], "laser")
    c = res.calibration
    cal = {n: (c["estimate"][i], c["sigma"][i]) for i, n in enumerate(c["parameters"])}
    est, sig = cal["laser_scale"]
    assert abs(est) < 4 * sig and abs(est) < 0.005 and sig < 0.002, (est, sig)
    for name, truth in (("e_r", p.radius_error_right), ("e_l", p.radius_error_left)):
        e, s = cal[name]
        assert abs(e - truth) < 4 * s, (name, e, s)
