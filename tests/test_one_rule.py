"""One angle wrap and one line-flip rule (docs/design.md, 2), each stated once and used
everywhere: no module of fgslam/, factors/ or devices/ wraps an angle by an expression or a
function of its own (checked on planted code), the wraps of factors/geometry.py keep their
conventions, and the landmark models and the association compare lines by
:func:`factors.line.flips`."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

import factors.line
from factors.geometry import TWO_PI, wrap_angle, wrap_angle_half_open, wrap_angles
from fgslam.config.robot import AssociationParams
from fgslam.frontend.features import Feature
from fgslam.slam import association, models
from fgslam.slam.association import Candidate

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("fgslam", "factors", "devices")
HOME = Path("factors", "geometry.py")  # the one place an angle is wrapped by hand


def _is_two_pi(node: ast.AST) -> bool:
    """``2 * pi``, ``pi * 2``, ``2.0 * np.pi``, ``TWO_PI``, ``math.tau`` and the like."""
    name = node.attr if isinstance(node, ast.Attribute) else getattr(node, "id", None)
    if name in ("TWO_PI", "tau"):
        return True
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult):
        sides = (node.left, node.right)
        pi = [s for s in sides if (getattr(s, "attr", None) or getattr(s, "id", None)) == "pi"]
        two = [s for s in sides if isinstance(s, ast.Constant) and s.value == 2]
        return bool(pi and two)
    return False


def _callee(node: ast.Call) -> str:
    f = node.func
    return f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")


def wrap_sites(source: str) -> list[tuple[int, str]]:
    """(line, what) of every angle wrap written out in ``source``: ``x % (2 pi)``, a
    remainder/mod/fmod by 2 pi, ``arctan2(sin x, cos x)``, or a function named like a wrap."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mod):
            if _is_two_pi(node.right):
                found.append((node.lineno, "x % (2 pi)"))
        elif isinstance(node, ast.Call):
            name = _callee(node)
            if name in ("remainder", "mod", "fmod") and len(node.args) == 2:
                if _is_two_pi(node.args[1]):
                    found.append((node.lineno, f"{name}(x, 2 pi)"))
            elif name in ("arctan2", "atan2") and len(node.args) == 2:
                y, x = node.args
                if (
                    isinstance(y, ast.Call)
                    and isinstance(x, ast.Call)
                    and _callee(y) == "sin"
                    and _callee(x) == "cos"
                    and ast.dump(ast.Tuple(y.args)) == ast.dump(ast.Tuple(x.args))
                ):
                    found.append((node.lineno, "arctan2(sin x, cos x)"))
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            if "wrap" in node.name.lower():
                found.append((node.lineno, f"def {node.name}"))
    return found


def test_no_angle_is_wrapped_outside_factors_geometry():
    bad = []
    for pkg in SCANNED:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if rel == HOME:
                continue
            for line, what in wrap_sites(path.read_text()):
                bad.append(f"{rel}:{line}: {what}")
    assert not bad, "wrap with factors.geometry.wrap_angle(s) instead:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "code",
    [
        "import math\ny = math.remainder(x, 2 * math.pi)\n",
        "import numpy as np\ny = np.remainder(x + np.pi, 2 * np.pi) - np.pi\n",
        "import math\ny = (x + math.pi) % (2.0 * math.pi) - math.pi\n",
        "from math import pi\ny = (x + pi) % (pi * 2) - pi\n",
        "from factors.geometry import TWO_PI\ny = (x + 3.14) % TWO_PI\n",
        "import math\ny = math.fmod(x, math.tau)\n",
        "import numpy as np\ny = np.arctan2(np.sin(a + b), np.cos(a + b))\n",
        "def _wrap(a):\n    return a\n",
    ],
)
def test_a_planted_wrap_is_found(code):
    assert wrap_sites(code), code


def test_ordinary_code_is_not_a_wrap():
    code = (
        "import math\nimport numpy as np\n"
        "k = n % 2\nr = math.remainder(x, 0.5)\nphi = np.arctan2(dy, dx)\n"
        "h = math.atan2(np.sin(a).mean(), np.cos(b).mean())\nw = 2 * math.pi * f\n"
    )
    assert wrap_sites(code) == []


# ---------------------------------------------------------------- the wraps' conventions


def _angles(n: int = 20000) -> np.ndarray:
    rng = np.random.default_rng(32)
    edges = np.array([k * math.pi for k in range(-7, 8)])
    near = np.concatenate([np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf)])
    return np.concatenate(
        [rng.uniform(-100, 100, n), rng.normal(0, 1e-6, 200), edges, near, [0.0, -0.0, 1e12]]
    )


def test_wrap_angle_at_plus_and_minus_pi():
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == math.pi
    assert wrap_angle(TWO_PI) == 0.0
    assert wrap_angle(0.1) == 0.1  # exact: an angle inside is returned unchanged
    assert wrap_angle_half_open(math.pi) == -math.pi
    assert wrap_angle_half_open(-math.pi) == -math.pi


def test_wrap_angle_is_the_exact_remainder_in_minus_pi_pi():
    """(-pi, pi], and a - wrap(a) an integer multiple of 2 pi: the IEEE remainder's value,
    with -pi taken to pi; scalar and vectorised give the same bits."""
    a = _angles()
    w = np.array([wrap_angle(float(v)) for v in a])
    assert np.all((w > -math.pi) & (w <= math.pi))
    want = np.array([math.remainder(float(v), TWO_PI) for v in a])
    want[want == -math.pi] = math.pi
    np.testing.assert_array_equal(w, want)
    np.testing.assert_array_equal(wrap_angles(a), w)
    inside = np.abs(a) < math.pi
    np.testing.assert_array_equal(w[inside], a[inside])


def test_wrap_angle_half_open_is_minus_pi_pi():
    a = _angles()
    w = wrap_angle_half_open(a)
    assert np.all((w >= -math.pi) & (w <= math.pi))
    # pi only where a + pi rounds (an ulp below -pi): the formula's, kept bit for bit
    top = a[w == math.pi]
    assert len(top) == 1 and top[0] == np.nextafter(-math.pi, -np.inf)
    k = (a - w) / TWO_PI
    small = np.abs(a) < 1e3
    np.testing.assert_allclose(k[small], np.round(k[small]), atol=1e-12)
    np.testing.assert_array_equal(w, [wrap_angle_half_open(float(v)) for v in a])
    assert np.all(np.abs(w - wrap_angles(a))[small & (np.abs(w) < 3.0)] < 1e-14)


# ---------------------------------------------------------------- the line-flip rule


def _line(z, cov=1e-4) -> Feature:
    return Feature("line", np.asarray(z, dtype=float), np.eye(2) * cov, laser_support=10)


def test_models_compare_the_two_forms_of_a_line_as_one_line():
    """A world line and its other form (alpha + pi, -d) differ by nothing, scalar and
    vectorised; a measurement of either form has a zero residual, in the pre-gate too."""
    rng = np.random.default_rng(4)
    for _ in range(50):
        lm = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(0.5, 8)])
        other = np.array([wrap_angle(lm[0] + math.pi), -lm[1]])
        np.testing.assert_allclose(models.difference("line", lm, other)[0], 0, atol=1e-12)
        np.testing.assert_allclose(models.differences("line", lm, other[None]), 0, atol=1e-12)
        pose = rng.uniform([-2, -2, -math.pi], [2, 2, math.pi])
        z = factors.line.predict_line(pose, lm)[0]
        for w in (lm, other):
            for zz in (z, [z[0] + math.pi, -z[1]]):
                zz = np.asarray(zz, dtype=float)
                e = models.residual("line", pose, w, zz)[0]
                np.testing.assert_allclose(e, 0, atol=1e-9)
                E = models.residuals("line", pose, w[None], zz)
                np.testing.assert_allclose(E, 0, atol=1e-9)


def _associate_flipped() -> list:
    """A wall 3 m ahead, its landmark stored in the other form (alpha + pi, -d)."""
    lm = np.array([wrap_angle(0.0 + math.pi), -3.0])
    means = {0: lm}

    def estimate(lids):
        P = np.eye(3 + 2 * len(lids)) * 1e-6
        return {i: means[i] for i in lids}, P

    out = association.associate(
        [_line((0.0, 3.0))],
        np.zeros(3),
        [Candidate(0, "line")],
        means,
        estimate,
        AssociationParams(method="nn"),
    )
    return out.pairs


def test_the_association_pairs_the_two_forms_of_a_line_by_flips(monkeypatch):
    """The association pairs a measured wall with its landmark stored in the other form;
    with factors.line.flips replaced by a rule that never flips it no longer does: the
    comparison goes through that one function."""
    assert _associate_flipped() == [0]
    monkeypatch.setattr(factors.line, "flips", lambda e: np.abs(e) > 10.0)
    assert _associate_flipped() == [None]
    lm, other = np.array([0.3, 2.0]), np.array([0.3 - math.pi, -2.0])
    assert np.abs(models.differences("line", lm, other[None])).max() > 3.0
