"""Robot configuration: defaults, overrides and one-line errors naming file and key."""

from __future__ import annotations

import dataclasses
import math

import pytest

from fgslam.config import ConfigError, load_config


def test_default_is_the_papers_robot():
    cfg = load_config()
    assert cfg.odometry.encoder_steps_per_rev == 2000
    assert cfg.odometry.sample_period == pytest.approx(0.01)
    assert cfg.laser.n_beams == 361 and cfg.laser.fov_deg == 180
    assert cfg.laser.range_resolution == pytest.approx(0.05)
    assert 1 / cfg.laser.scan_period == pytest.approx(4.77, abs=0.01)
    assert cfg.sonar.sigma_bearing == pytest.approx(math.radians(2))
    assert cfg.sonar.sigma_sound_rel == pytest.approx(0.02)
    assert len(cfg.sonar.arrays) == 2
    b = cfg.laser.bearings
    assert b[0] == pytest.approx(-math.pi / 2) and b[-1] == pytest.approx(math.pi / 2)
    assert b[1] - b[0] == pytest.approx(math.radians(0.5))


def write(tmp_path, text):
    p = tmp_path / "robot.toml"
    p.write_text(text)
    return p


def test_override_subset(tmp_path):
    p = write(tmp_path, "[odometry]\nwheelbase = 0.5\n[laser.mount]\nx = 0.3\n")
    cfg = load_config(p)
    assert cfg.odometry.wheelbase == 0.5
    assert cfg.laser.mount.x == 0.3 and cfg.laser.mount.yaw_deg == 0.0  # rest kept
    assert cfg.odometry.k_r == load_config().odometry.k_r
    assert cfg.source == str(p)


def test_integer_accepted_for_float(tmp_path):
    assert load_config(write(tmp_path, "[laser]\nmax_range = 20\n")).laser.max_range == 20.0


def test_sonar_arrays_replaced_whole(tmp_path):
    text = (
        '[[sonar.arrays]]\nname = "front"\nmount = { x = 0.2, y = 0.0, yaw_deg = 0.0 }\n'
        "pan_min_deg = -60.0\npan_max_deg = 60.0\nsweep_period = 8.0\n"
    )
    cfg = load_config(write(tmp_path, text))
    assert [a.name for a in cfg.sonar.arrays] == ["front"]


@pytest.mark.parametrize(
    "text, key, expected",
    [
        ("[odometry]\nwheelbse = 0.5\n", "odometry.wheelbse", "unknown key"),
        ("[lidar]\nx = 1\n", "lidar", "unknown key"),
        ('[odometry]\nwheelbase = "wide"\n', "odometry.wheelbase", "expected a number"),
        (
            "[odometry]\nencoder_steps_per_rev = 2000.5\n",
            "odometry.encoder_steps_per_rev",
            "integer",
        ),
        ("[odometry]\nwheelbase = -0.4\n", "odometry.wheelbase", "positive"),
        ("[odometry]\nk_r = -0.1\n", "odometry.k_r", "non-negative"),
        ("[laser]\nmax_range = nan\n", "laser.max_range", "finite"),
        ("[laser]\nmount = 3\n", "laser.mount", "expected a table"),
        ("[laser.mount]\nyaw = 3\n", "laser.mount.yaw", "unknown key"),
        ('[[sonar.arrays]]\nname = "a"\n', "sonar.arrays.mount", "missing required key"),
        ("[robot]\nname = 3\n", "robot.name", "expected a string"),
        ("[odometry]\nk_d = true\n", "odometry.k_d", "expected a number"),
    ],
)
def test_errors_name_file_and_key(tmp_path, text, key, expected):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert "\n" not in msg
    assert str(p) in msg and f"'{key}'" in msg and expected in msg


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "[odometry\n"))
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.toml")


def test_inconsistent_values(tmp_path):
    with pytest.raises(ConfigError, match="delay_max"):
        load_config(write(tmp_path, "[laser]\ndelay_min = 0.1\ndelay_max = 0.05\n"))


@pytest.mark.parametrize(
    "text, msg",
    [
        ("[odometry]\nencoder_steps_per_rev = 100000000000000000\n", "encoder_steps_per_rev"),
        ("[laser]\nfov_deg = 720.0\n", "laser.fov_deg': 720.0 is not plausible"),
        ("[laser]\nmount = { x = 1e12, y = 0.0, yaw_deg = 0.0 }\n", "laser.mount.x"),
    ],
)
def test_absurd_values_are_refused(tmp_path, text, msg):
    with pytest.raises(ConfigError, match=msg) as exc:
        load_config(write(tmp_path, text))
    assert "\n" not in str(exc.value) and str(tmp_path) in str(exc.value)


def test_override_is_key_by_key_on_the_base(tmp_path):
    """A partial file changes only its keys of the given base (a log's configuration)."""
    from fgslam.config import override_config
    from fgslam.io.readers.common import derived_config

    base = derived_config(180, 180.0)  # a CARMEN laser
    cfg = override_config(base, write(tmp_path, "[odometry]\nk_r = 0.2\n"))
    assert cfg.odometry.k_r == 0.2 and cfg.laser.n_beams == 180
    assert cfg.odometry.wheelbase == base.odometry.wheelbase
    assert cfg.source == str(tmp_path / "robot.toml")
    assert override_config(base, None) is base


def test_contradicting_the_log_names_both(tmp_path):
    from fgslam.config import check_against_log, override_config

    log_cfg = load_config()
    cfg = override_config(log_cfg, write(tmp_path, "[laser]\nn_beams = 180\n"))
    with pytest.raises(ConfigError, match=r"n_beams = 180 contradicts the log x.log \(361"):
        check_against_log(cfg, log_cfg, "x.log")
    one = log_cfg.to_dict()["sonar"]["arrays"][:1]
    import tomli_w

    p = write(tmp_path, tomli_w.dumps({"sonar": {"arrays": one}}))
    with pytest.raises(ConfigError, match=r"1 sonar arrays, but the log x\.log has 2"):
        check_against_log(override_config(log_cfg, p), log_cfg, "x.log")
    check_against_log(log_cfg, log_cfg, "x.log")


def test_frontend_thresholds_pls_defaults_exactly_as_before():
    """The paper's PLS (361 beams over 180 deg, sigma 2 cm, 30 m) derives exactly the
    front end's and the map's former constants."""
    from fgslam.config.robot import FrontEndParams, MapParams, SegmentParams
    from fgslam.frontend.pipeline import frontend_params

    cfg = load_config()
    # the thresholds (the laser's calibration choice is not one of them)
    assert dataclasses.replace(frontend_params(cfg), range_calibration="off") == FrontEndParams()
    seg = frontend_params(cfg).segment
    assert (seg.min_points, seg.max_range, seg.outlier, seg.spread) == (8, 8.0, 0.07, 0.025)
    assert seg == SegmentParams()
    assert MapParams.from_config(cfg) == MapParams()
    assert MapParams.from_config(cfg).max_range == 10.0


def test_frontend_thresholds_derived_from_another_laser(tmp_path):
    """A SICK LMS at 1 deg, sigma 1 cm, 80 m (the CARMEN logs): 4 beams, 3.5 cm, 1.25 cm,
    4 m (beams 7 cm apart), 6 m; configured values win over derived ones."""
    import dataclasses

    from fgslam.config import frontend_thresholds
    from fgslam.io.readers.common import derived_config

    cfg = derived_config(181, 180.0, max_range=80.0, sigma_range=0.01)
    assert frontend_thresholds(cfg) == pytest.approx(
        {
            "min_points": 4,
            "outlier": 0.035,
            "spread": 0.0125,
            "max_line_range": 4.0,
            "map_max_range": 10.0,
            "residual_level": 0.99,
        }
    )
    assert frontend_thresholds(load_config())["residual_level"] is None  # PLS: off
    f = tmp_path / "r.toml"
    f.write_text("[frontend]\nmax_line_range = 12.0\nmin_points = 6\n")
    user = load_config(f)
    th = frontend_thresholds(dataclasses.replace(user, laser=cfg.laser))
    assert th["max_line_range"] == 12.0 and th["min_points"] == 6 and th["map_max_range"] == 14.0
    f.write_text("[frontend]\nmin_points = -1\n")
    with pytest.raises(ConfigError, match=r"frontend\.min_points"):
        load_config(f)


def test_old_configuration_without_new_keys_still_loads():
    """A log header written before the odometry error model and the [frontend] section
    existed: the new keys take their defaults."""
    d = load_config().to_dict()
    del d["frontend"]
    for k in ("alpha1", "alpha2", "alpha3", "alpha4", "alpha5", "hole_tolerance"):
        del d["odometry"][k]
    from fgslam.config import from_dict

    cfg = from_dict(d, "old header")
    assert cfg.odometry.alpha1 == 0.0 and cfg.frontend.min_points == 0
