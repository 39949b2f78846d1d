"""Shared test helpers."""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
import pytest
from hypothesis import settings

# Property tests draw the same examples on every run (CI must not depend on luck); each
# test's own settings (examples, deadline) inherit this.
settings.register_profile("deterministic", derandomize=True)
settings.load_profile("deterministic")


def numeric_jacobian(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, eps: float = 1e-6):
    """Central-difference Jacobian of f at x (plain vectors)."""
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x))
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        d = np.zeros_like(x)
        d[i] = eps
        J[:, i] = (np.asarray(f(x + d)) - np.asarray(f(x - d))) / (2 * eps)
    return J


def factor_numeric_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values, eps=1e-6):
    """Numerical Jacobians of a factor's unwhitened error w.r.t. the local coordinates
    (retract) of each of its variables, in key order."""
    out = []
    for key in factor.keys():
        try:
            v0 = values.atPose2(key)
            n = 3
        except RuntimeError:
            v0 = values.atVector(key)
            n = v0.size
        J = np.zeros((factor.dim(), n))
        for i in range(n):
            cols = []
            for sgn in (1.0, -1.0):
                d = np.zeros(n)
                d[i] = sgn * eps
                vals = gtsam.Values(values)
                if isinstance(v0, gtsam.Pose2):
                    vals.update(key, v0.retract(d))
                else:
                    vals.update(key, v0 + d)
                cols.append(factor.unwhitenedError(vals))
            J[:, i] = (cols[0] - cols[1]) / (2 * eps)
        out.append(J)
    return out


def factor_analytic_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values):
    """Analytic Jacobians of the unwhitened error in key order (linearize whitens: undo it)."""
    A, _ = factor.linearize(values).jacobian()
    A = np.linalg.solve(factor.noiseModel().R(), A)
    out, col = [], 0
    for key in factor.keys():
        try:
            values.atPose2(key)
            n = 3
        except RuntimeError:
            n = values.atVector(key).size
        out.append(A[:, col : col + n])
        col += n
    return out


@pytest.fixture
def one_line_error(tmp_path, monkeypatch, capsys) -> Callable[[list[str], str], None]:
    """``check(argv, msg)``: ``fgslam ARGV``, run in this process in ``tmp_path``, fails with
    status 2 and one error line (no traceback) that says ``msg``."""
    from fgslam.cli import main

    def check(argv: list[str], msg: str) -> None:
        monkeypatch.chdir(tmp_path)
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and "\n" not in err and "Traceback" not in err

    return check


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
