"""One configuration path (issue 32, item 2; docs/design.md, 2): every parameter of every
component is a key of the TOML configuration (or linked to one), its default written once
beside its field, and ``fgslam config --show`` lists it with its default and unit."""

from __future__ import annotations

import dataclasses
import math

import pytest
from scipy.stats import chi2

from fgslam import config as c
from fgslam.choices import CHOICES
from fgslam.config import ConfigError, load_config
from fgslam.config.load import _CHOICES
from fgslam.config.robot import (
    AssociationParams,
    FrontEndParams,
    GraphParams,
    KeyframeParams,
    LoopParams,
    MapParams,
    SegmentParams,
)
from fgslam.frontend.pipeline import frontend_params
from fgslam.scanmatch import MatchParams
from fgslam.slam.runner import SlamPipeline

# (section path, class, how a component gets it)
SECTIONS = [
    ("features", FrontEndParams, FrontEndParams.from_config),
    ("features.segment", SegmentParams, SegmentParams.from_config),
    ("keyframes", KeyframeParams, KeyframeParams.from_config),
    ("matcher", MatchParams, MatchParams.from_config),
    ("loops", LoopParams, LoopParams.from_config),
    ("association", AssociationParams, AssociationParams.from_config),
    ("map", MapParams, MapParams.from_config),
    ("graph", GraphParams, GraphParams.from_config),
]


def _other(value, key: str):
    """A valid value of a key other than ``value``."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, str):
        section, name = key.rsplit(".", 1)
        choices = CHOICES.get((section, name)) or _CHOICES[key]
        return next(x for x in choices if x != value)
    if isinstance(value, tuple):
        return tuple(_other(v, key) for v in value)
    if isinstance(value, int):
        return value + 1
    return 0.5 if value >= 0.9 else round(value * 1.5 + 0.05, 6)


def _toml(key: str, value) -> str:
    import tomli_w

    section, name = key.rsplit(".", 1)
    out: dict = {}
    d = out
    for part in section.split("."):
        d = d.setdefault(part, {})
    d[name] = list(value) if isinstance(value, tuple) else value
    return tomli_w.dumps(out)


def _load(tmp_path, text: str):
    p = tmp_path / "robot.toml"
    p.write_text(text)
    return load_config(p)


def _get(cfg, path: str):
    obj = cfg
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


OWN_KEYS = [
    (section, f.name)
    for section, cls, _ in SECTIONS
    for f in c.keys(cls)
    if f.name != "segment"  # a section of its own
]


@pytest.mark.parametrize("section, name", OWN_KEYS)
def test_every_component_key_reaches_its_component(tmp_path, section, name):
    """Set the key in a TOML file, load it, build the component: the value arrives."""
    cls, build = next((cl, b) for s, cl, b in SECTIONS if s == section)
    key = f"{section}.{name}"
    value = _other(getattr(cls(), name), key)
    cfg = _load(tmp_path, _toml(key, value))
    assert getattr(build(cfg), name) == value
    # the others keep their defaults
    rest = {f.name for f in c.keys(cls)} - {name, "segment"}
    assert all(getattr(build(cfg), k) == getattr(build(load_config()), k) for k in rest)


LINKS = [
    (section, f.name, f.metadata["from"])
    for section, cls, _ in SECTIONS
    for f in dataclasses.fields(cls)
    if "from" in f.metadata
]
# how a linked field follows its key when that is not equality
CONVERT = {
    "scanmatch.keyframe_angle_deg": math.radians,
    "scanmatch.loop_closures": lambda v: v == "on",
    "scanmatch.model_error_theta_deg": math.radians,
}


@pytest.mark.parametrize("section, name, key", LINKS)
def test_every_linked_parameter_follows_its_key(tmp_path, section, name, key):
    """A component's parameter set by another section's key (converted, or derived from the
    sensor unless the key is set) takes the key's value."""
    default = _get(load_config(), key)
    if key == "laser.sigma_range":
        value = 0.03
    elif key == "laser.max_range":
        value = 20.0
    elif isinstance(default, (int, float)) and not isinstance(default, bool) and default <= 0:
        value = 0.1 if "theta" in key else (5 if isinstance(default, int) else 0.3)
    else:
        value = _other(default, key)
    cfg = _load(tmp_path, _toml(key, value))
    assert _get(cfg, f"{section}.{name}") == pytest.approx(CONVERT.get(key, lambda v: v)(value))


@pytest.mark.parametrize("section, name, key", LINKS)
def test_a_linked_parameter_is_refused_in_its_own_section(tmp_path, section, name, key):
    cls = next(cl for s, cl, _ in SECTIONS if s == section)
    with pytest.raises(ConfigError) as exc:
        _load(tmp_path, _toml(f"{section}.{name}", getattr(cls(), name) or 1))
    msg = str(exc.value)
    assert "\n" not in msg and f"'{section}.{name}'" in msg and f"'{key}'" in msg


@pytest.mark.parametrize(
    "text, key, expected",
    [
        ("[map]\ngate = 0.9\n", "map.gate", "unknown key"),
        ("[loops]\nradius_m = 3.0\n", "loops.radius_m", "unknown key"),
        ("[matcher]\nsearch_xy = -0.3\n", "matcher.search_xy", "non-negative"),
        ("[association]\ngate_p = 1.5\n", "association.gate_p", "level in [0, 1)"),
        ('[association]\nmethod = "best"\n', "association.method", "expected one of jcbb, nn"),
        ("[association]\npregate = [0.3, 1.0]\n", "association.pregate", "expected 3 numbers"),
        ('[loops]\ndoubt = "yes"\n', "loops.doubt", "true or false"),
        ("[keyframes]\nlocal_map = 1.5\n", "keyframes.local_map", "integer"),
        ("[features.segment]\njumps = 0.3\n", "features.segment.jumps", "unknown key"),
        ("[scanmatch]\nmotion_gate_p = 0.0\n", "scanmatch.motion_gate_p", "(0, 1)"),
    ],
)
def test_unknown_or_invalid_keys_are_refused(tmp_path, text, key, expected):
    with pytest.raises(ConfigError) as exc:
        _load(tmp_path, text)
    msg = str(exc.value)
    assert "\n" not in msg and str(tmp_path) in msg and f"'{key}'" in msg and expected in msg


def test_the_components_defaults_are_written_once():
    """The shipped configuration builds exactly the classes' defaults (the PLS derives the
    linked thresholds' defaults), and the runner builds its components from it."""
    cfg = load_config()
    assert MapParams.from_config(cfg) == MapParams()
    assert KeyframeParams.from_config(cfg) == KeyframeParams()
    assert LoopParams.from_config(cfg) == LoopParams()
    assert AssociationParams.from_config(cfg) == AssociationParams()
    assert GraphParams.from_config(cfg) == GraphParams()
    assert MapParams().association_params() == AssociationParams()
    assert SegmentParams.from_config(cfg) == SegmentParams()
    # the shipped laser estimates its range offset; the class's default is a header's without
    assert dataclasses.replace(frontend_params(cfg), range_calibration="off") == FrontEndParams()
    # the matcher derives from the laser as it did before there was a [matcher] section
    pls = MatchParams.for_laser(0.02, math.radians(0.5), 30.0)
    assert MatchParams.from_config(cfg) == pls
    pipe = SlamPipeline(cfg, ["ekf", "isam2"])
    assert pipe.keyframe_params == cfg.keyframes
    assert pipe.frontend.p == cfg.features
    assert pipe.scan_odometry.p == cfg.keyframes
    assert pipe.sessions["ekf"].p == cfg.map and pipe.sessions["graph"].p == cfg.map
    assert pipe.sessions["graph"].loops.p == cfg.loops
    assert pipe.sessions["graph"].loops.mp == cfg.matcher


def test_linked_defaults_are_their_keys_defaults():
    """A linked field's default is its key's (a reference, not a second literal), except
    where the key derives its value from the sensor (the class's default is then the PLS's
    value, checked above, or a matcher's without a sensor)."""
    shipped = load_config()
    for section, name, key in LINKS:
        cls = next(cl for s, cl, _ in SECTIONS if s == section)
        sect, kname = key.split(".")
        f = next(f for f in dataclasses.fields(getattr(shipped, sect)) if f.name == kname)
        if f.metadata.get("derive") or section == "matcher":
            continue
        want = CONVERT.get(key, lambda v: v)(f.default)
        if key == "frontend.residual_level":
            want = f.default or None
        got = getattr(cls(), name)
        assert got == want, (section, name, key)


def test_motion_gate_p_reaches_the_ekf(tmp_path):
    cfg = _load(tmp_path, "[scanmatch]\nmotion_gate_p = 0.99\n")
    ekf = SlamPipeline(cfg, ["ekf"]).sessions["ekf"].be
    assert ekf.motion_gate == pytest.approx(chi2.ppf(0.99, 3))
    assert SlamPipeline(load_config(), ["ekf"]).sessions["ekf"].be.motion_gate == pytest.approx(
        chi2.ppf(0.999, 3)
    )


def test_the_sections_survive_a_log_header(tmp_path):
    """A configuration with the components' keys set goes through to_dict (a log header)
    and back unchanged; the linked fields are no keys of the header."""
    text = "[map]\nunseen_limit = 7\n[loops]\ndoubt = false\n[matcher]\nsearch_xy = 0.4\n"
    cfg = _load(tmp_path, text)
    d = cfg.to_dict()
    assert d["map"]["unseen_limit"] == 7 and "max_range" not in d["map"]
    assert "distance" not in d["keyframes"] and "min_points" not in d["features"]["segment"]
    assert c.from_dict(d, "header") == cfg
    # a header written before the sections existed takes the defaults
    for name in c.COMPONENTS:
        del d[name]
    assert c.from_dict(d, "old header").map == load_config().map


def test_replacing_a_section_resolves_the_links_again():
    from fgslam.io.readers.common import derived_config

    lms = derived_config(181, 180.0)  # the CARMEN logs' SICK LMS: sigma 1 cm, 1 deg
    assert lms.features.segment.min_points == 4 and lms.map.max_range == 10.0  # the floor
    fine = derived_config(721, 180.0)  # 0.25 deg: 16 m lines, candidates 2 m beyond
    assert fine.frontend.max_line_range == 0.0 and fine.map.max_range == 18.0
    assert lms.matcher.sigma_range == c.SICK_LMS_SIGMA_RANGE == 0.01
    assert lms.matcher.floor_theta == pytest.approx(math.radians(1.0))


def test_the_association_path_keeps_the_sensor_derived_map_range():
    """Given an association (as `fgslam run` always is) the map keeps the range derived from
    the laser, and every other [map] key arrives."""
    from fgslam.io.readers.common import derived_config

    fine = derived_config(721, 180.0)
    lms = dataclasses.replace(fine, map=dataclasses.replace(fine.map, unseen_limit=9))
    assert SlamPipeline(lms, ["ekf"]).sessions["ekf"].p.max_range == 18.0
    via = SlamPipeline(lms, ["ekf"], association="nn").sessions["ekf"].p
    assert via.max_range == 18.0 and via.association == "nn" and via.unseen_limit == 9


def _show(capsys, cfg=None) -> str:
    from fgslam.cli.config import show

    show(cfg or load_config())
    return capsys.readouterr().out


def _all_fields(obj, path=""):
    """(section path, field) of every dataclass field of every section of ``obj``."""
    for f in dataclasses.fields(obj):
        if f.name == "source":
            continue
        value = getattr(obj, f.name)
        here = f"{path}.{f.name}" if path else f.name
        if dataclasses.is_dataclass(value):
            yield from _all_fields(value, here)
        elif isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
            for i, item in enumerate(value):
                yield from _all_fields(item, f"{here}.{i}")
        else:
            yield path, f


def test_show_lists_every_field_with_its_default_and_unit(capsys):
    out = _show(capsys)
    sections: dict[str, list[str]] = {}
    current = None
    for line in out.splitlines():
        if line.startswith("["):
            current = line.strip("[]")
            sections[current] = []
        elif current and line.strip() and not line.startswith("# every"):
            sections[current].append(line)
    fields = list(_all_fields(load_config()))
    assert len(fields) > 200
    for section, f in fields:
        rows = [r for r in sections[section] if r.lstrip("# ").startswith(f"{f.name} = ")]
        assert len(rows) == 1, (section, f.name)
        assert "default " in rows[0]
        unit, meaning = f.metadata["unit"], f.metadata["doc"]
        assert unit and meaning, f"{section}.{f.name} has no unit or meaning"
        assert f"; {unit}; {meaning}" in rows[0]


def test_show_gives_the_derived_values_and_the_links(capsys, tmp_path):
    out = _show(capsys)
    assert "min_points = 0" in out and "derived 8 (ceil(4 deg / beam step))" in out
    assert "# motion_gate_p = 0.999" in out and "= scanmatch.motion_gate_p" in out
    cfg = _load(tmp_path, "[laser]\nsigma_range = 0.01\n[frontend]\nspread = 0.03\n")
    out = _show(capsys, cfg)
    assert "derived 0.035 (3.5 sigma_range)" in out  # outlier, derived for this laser
    spread = next(r for r in out.splitlines() if r.startswith("spread = "))
    assert "spread = 0.03 " in spread and "derived" not in spread  # set, so not derived


def test_every_derivation_rule_has_its_value():
    cfg = load_config()
    values = c.derived_values(cfg)
    rules = [
        f"{section}.{f.name}" if section else f.name
        for section, f in _all_fields(cfg)
        if f.metadata.get("derive")
    ]
    assert sorted(rules) == sorted(values)
    assert values["frontend.min_points"] == cfg.features.segment.min_points
    assert values["frontend.map_max_range"] == cfg.map.max_range
    assert values["scanmatch.match_resolution"] == cfg.matcher.resolution


def test_show_as_json(capsys):
    import json

    from fgslam.cli.config import show

    show(load_config(), as_json=True)
    rows = json.loads(capsys.readouterr().out)
    keys = {r["key"] for r in rows}
    assert "map.unseen_limit" in keys and "keyframes.motion_gate_p" in keys
    assert "sonar.arrays.1.mount.yaw_deg" in keys


def test_the_shipped_tuning_sections_repeat_no_other_default():
    """[frontend] and [scanmatch] of the shipped file hold the fields' defaults (and no other
    value: the file's keys are also the fuzzers' schema, tests/test_fuzz_inputs.py)."""
    import tomllib

    shipped = tomllib.loads(c.default_config_text())
    for name, cls in (("frontend", c.FrontendConfig), ("scanmatch", c.ScanMatchConfig)):
        defaults = {f.name: f.default for f in c.keys(cls)}
        assert {k: defaults[k] for k in shipped[name]} == shipped[name]


@pytest.mark.parametrize("name", [f.name for f in c.keys(GraphParams)])
def test_every_graph_key_reaches_the_isam2_backend(tmp_path, name):
    """A ``[graph]`` key set in a TOML file arrives in the iSAM2 backend the runner builds
    (its own attribute, or iSAM2's parameters for the relinearisation and factorisation)."""
    from fgslam.slam.runner import make_backend

    key = f"graph.{name}"
    value = _other(getattr(GraphParams(), name), key)
    be = make_backend("isam2", _load(tmp_path, _toml(key, value)))
    got = {
        "relinearize_skip": lambda: be._params.relinearizeSkip,
        "factorization": lambda: str(be._params.getFactorization()),
        "relinearize_threshold": lambda: be._relinearize_threshold,
    }.get(name, lambda: getattr(be, name))()
    assert got == value


def test_the_robust_kernels_are_listed_once():
    """The configuration's choices of kernel are the noise models' (factors cannot import
    fgslam, so the tuple is written in both places; this keeps them one list)."""
    from factors.noise import ROBUST_KERNELS
    from fgslam.choices import ROBUST_CHOICES

    assert ROBUST_CHOICES == ROBUST_KERNELS
