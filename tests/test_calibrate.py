"""fgslam calibrate: maximum-likelihood fit of the odometry's motion error model."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from readers_helpers import carmen_text

from factors.odometry import OdometryParams, integrate_poses, sample_paths
from fgslam.cli import main
from fgslam.config import load_config
from fgslam.evaluation.calibrate import fit_alphas, motion_covariances
from fgslam.io.formats import open_log


def test_fit_recovers_the_alphas_of_simulated_errors():
    """400 one-second motions (arcs and turns on the spot), each reference = the nominal
    odometry plus an error drawn from the motion error model with known alphas: the
    maximum-likelihood fit recovers them (the identifiable ones within 30 %) and the NEES
    after the fit is 3."""
    rng = np.random.default_rng(8)
    true = OdometryParams(
        0.5, 0.0, 0.0, 0.0, alpha1=0.02, alpha2=0.005, alpha3=0.004, alpha4=0.002, alpha5=0.001
    )
    samples, pairs, errs = [], [], []
    t = 0.0
    for _ in range(400):
        v, w = rng.uniform(0.0, 0.8), rng.uniform(-1.5, 1.5)
        lr = np.full(10, (v + 0.25 * w) * 0.1)
        ll = np.full(10, (v - 0.25 * w) * 0.1)
        ts = t + 0.1 * np.arange(1, 11)
        samples += list(zip(ts, lr, ll, strict=True))
        nominal = integrate_poses(lr, ll, 0.5)[-1]
        noisy = sample_paths(lr, ll, true, 1, rng)[0]
        pairs.append((t, t + 1.0))
        e = noisy - nominal
        errs.append(e)
        t += 1.0
    samples = np.array(samples)
    ok, _, C = motion_covariances(samples, np.array(pairs), true)
    assert ok.all()
    a = fit_alphas(np.array(errs), C)
    np.testing.assert_allclose(a[[0, 2, 4]], [0.02, 0.004, 0.001], rtol=0.3)
    assert a[1] == pytest.approx(0.005, rel=0.6) and a[3] == pytest.approx(0.002, rel=0.6)


def test_calibrate_command_writes_a_loadable_snippet(tmp_path, capsys):
    """On a corrected synthetic log with a 2 cm / 0.01 rad error per step, against its own
    reference poses: NEES before and after printed, the snippet is valid TOML that
    `fgslam run --config` overlays on the log's configuration, and after the fit the NEES
    is near 3 (it was far from it before)."""
    f = tmp_path / "room.log"
    f.write_text(carmen_text(corrected=True, n=60, odo_error=(0.02, 0.01, 0.01)))
    out = tmp_path / "odo.toml"
    assert main(["calibrate", str(f), "--reference", str(f), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "relative motions: odometry NEES" in text
    snippet = tomllib.loads(out.read_text())
    assert snippet["odometry"]["k_r"] == 0.0 and snippet["odometry"]["alpha3"] >= 0
    base = open_log(f).config
    cfg = load_config(out, base)
    assert cfg.odometry.wheelbase == base.odometry.wheelbase  # the log's, not the PLS's
    assert cfg.laser == base.laser and cfg.odometry.alpha1 == snippet["odometry"]["alpha1"]
    import re

    m = re.search(r"(\d+) relative motions: .* before, ([0-9.e+]+) \(", text)
    assert m and int(m.group(1)) == 59 and 2.0 < float(m.group(2)) < 4.0


def test_calibrate_errors(tmp_path, capsys):
    f = tmp_path / "room.log"
    f.write_text(carmen_text(corrected=True))
    rel = tmp_path / "far.relations"
    rel.write_text("1000 1001 1 0 0 0 0 0\n")
    assert main(["calibrate", str(f), "--reference", str(rel)]) == 2
    assert "nothing to calibrate against" in capsys.readouterr().err
