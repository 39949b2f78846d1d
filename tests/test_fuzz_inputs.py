"""A robot configuration file is read or refused with one ConfigError, never another
exception (issue "Bad input never escapes", item 5: what ``experiments/fuzz_inputs.py``
found on the configuration path), and a configuration that loads gives every parameter a
run derives from it.

Regression tests of the campaign's escapes, then a hypothesis fuzz test of ``load_config``
on mutated TOML text: the default file with values replaced by hostile ones, keys and
sections dropped, sonar arrays removed or emptied, or a small override file."""

from __future__ import annotations

import re
import warnings

import pytest
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st

from fgslam import config as c
from fgslam.config import ConfigError, load_config
from fgslam.config.robot import KeyframeParams, LoopParams, MapParams
from fgslam.scanmatch import MatchParams


def _derived(cfg: c.RobotConfig) -> None:
    """What ``fgslam config`` prints and what a run derives from the configuration."""
    tomli_w.dumps(cfg.to_dict())
    c.frontend_thresholds(cfg)
    MatchParams.from_config(cfg)
    KeyframeParams.from_config(cfg)
    LoopParams.from_config(cfg)
    MapParams.from_config(cfg)
    cfg.odometry.params()
    for section in (cfg.odometry, cfg.laser, cfg.sonar):
        section.calibration_prior()
    assert cfg.laser.bearings.size == cfg.laser.n_beams
    assert cfg.laser.scan_period > 0


def _outcome(tmp_path, text: str) -> str:
    """'loaded' or 'refused' (a ConfigError naming the file); any other exception and any
    warning fails the test."""
    p = tmp_path / "robot.toml"
    p.write_text(text, encoding="utf-8", errors="surrogateescape")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            cfg = load_config(p)
        except ConfigError as exc:
            msg = str(exc)
            assert msg.startswith(str(p)) and "\n" not in msg, msg
            return "refused"
        _derived(cfg)
    return "loaded"


# -- the campaign's escapes (each failed on a08788f)


@pytest.mark.parametrize(
    "text",
    [
        "[laser]\nmount = " + "[" * 5000 + "]" * 5000 + "\n",  # arrays nested too deeply
        "[frontend]\nspread = " + "{ a = " * 2000 + "1" + " }" * 2000 + "\n",  # inline tables
    ],
    ids=["arrays", "inline-tables"],
)
def test_nesting_beyond_the_recursion_limit_is_refused(tmp_path, text):
    p = tmp_path / "robot.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_config(p)


@pytest.mark.parametrize(
    "laser",
    [
        "fov_deg = 5e-324",  # the beam step underflows to 0: ZeroDivisionError
        "fov_deg = 1e-305\nn_beams = 1000",  # 0.07 m / step overflows: OverflowError
        "fov_deg = 1e-9\nn_beams = 100000",
    ],
)
def test_a_beam_step_no_scanner_has_is_refused(tmp_path, laser):
    p = tmp_path / "robot.toml"
    p.write_text(f"[laser]\n{laser}\n")
    with pytest.raises(ConfigError, match=r"laser.fov_deg.*beam step"):
        load_config(p)


def test_the_finest_plausible_scanner_still_loads(tmp_path):
    p = tmp_path / "robot.toml"
    p.write_text("[laser]\nfov_deg = 360.0\nn_beams = 100000\n")
    cfg = load_config(p)
    _derived(cfg)
    assert c.frontend_thresholds(cfg)["min_points"] > 0


# -- fuzzing

VALUES = (
    "nan", "+nan", "-nan", "inf", "-inf", "1e400", "-1e400", "5e-324", "1e-320", "1e-300",
    "0", "0.0", "-0.0", "-1", "1", "2", "1e308", "-1e308", "1e9", "1e10", "100000", "100001",
    "360.0000001", "9223372036854775807", "-9223372036854775808", "0x7FFFFFFF", "true",
    '"x"', '""', "[]", "[1, 2]", "[nan, nan, nan]", "[0.0, 0.0, 0.0]", "[1e400, 1, 1]",
    "{}", "{ x = 1 }", "{ x = nan, y = 0, yaw_deg = 0 }", "{ x = 0, y = 0 }", "1979-05-27",
    "[" * 3000 + "]" * 3000,
)  # fmt: skip
_KEY_LINE = re.compile(r"^([A-Za-z_]\w*)(\s*=\s*)(.*)$")
DEFAULT_LINES = c.default_config_text().splitlines()
SCHEMA: list[tuple[str, str]] = []
_section = ""
for _ln in DEFAULT_LINES:
    if _ln.startswith("["):
        _section = _ln.strip("[] ")
    elif m := _KEY_LINE.match(_ln):
        SCHEMA.append((_section, m.group(1)))


@st.composite
def mutated_default(draw) -> str:
    """The default file with one to three changes."""
    lines = list(DEFAULT_LINES)
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["value", "value", "value", "drop", "arrays", "bytes"]))
        keyed = [i for i, ln in enumerate(lines) if _KEY_LINE.match(ln)]
        if op == "value" and keyed:
            k = draw(st.sampled_from(keyed))
            m = _KEY_LINE.match(lines[k])
            assert m is not None
            new = draw(st.one_of(st.sampled_from(VALUES), st.floats().map(repr)))
            lines[k] = f"{m.group(1)}{m.group(2)}{new}"
        elif op == "drop" and lines:
            del lines[draw(st.integers(0, len(lines) - 1))]
        elif op == "arrays":
            if draw(st.booleans()):
                lines = [ln for ln in lines if ln.strip() != "[[sonar.arrays]]"]
            else:
                k = lines.index("[sonar]") + 1 if "[sonar]" in lines else 0
                lines.insert(k, "arrays = " + draw(st.sampled_from(["[]", "[{}]", "1"])))
        else:
            k = draw(st.integers(0, max(0, len(lines) - 1)))
            lines.insert(k, draw(st.text(max_size=30)))
    return "\n".join(lines) + "\n"


@st.composite
def override_file(draw) -> str:
    """A small user file: one to four keys of the default file with hostile values."""
    picks = draw(st.lists(st.sampled_from(SCHEMA), min_size=1, max_size=4, unique=True))
    parts = []
    for section, key in sorted(picks):
        value = draw(st.one_of(st.sampled_from(VALUES), st.floats().map(repr), st.integers()))
        header = "[[sonar.arrays]]" if section == "sonar.arrays" else f"[{section}]"
        parts += [header, f"{key} = {value}"]
    return "\n".join(parts) + "\n"


@given(st.one_of(mutated_default(), override_file()))
@settings(max_examples=300, deadline=None)
def test_fuzz_config_toml(tmp_path_factory, text):
    assert _outcome(tmp_path_factory.mktemp("cfg"), text) in ("loaded", "refused")


# -- the campaign's escapes on the log paths (each a traceback on 0730085), through convert


def _convert(tmp_path, capsys, log) -> str:
    """``fgslam convert`` of ``log``: exit status 2 and one error line naming it."""
    from fgslam.cli import main

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw warning (an unclosed file) either
        rc = main(["convert", str(log), "--out", str(tmp_path / "o.log")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and log.name in err, err
    return err


@pytest.mark.parametrize("value", ["NaN", "-Infinity", "1e400"])
def test_native_header_with_a_number_json_cannot_hold(tmp_path, capsys, value):
    """A META value of NaN, Infinity or beyond a float: refused naming the line (it was
    read, then the log writer's strict JSON failed)."""
    from readers_helpers import write_native

    f = tmp_path / "n.log"
    write_native(f, n=5)
    lines = f.read_text().splitlines()
    lines.insert(3, f'META {{"x": {value}}}')
    f.write_text("\n".join(lines) + "\n")
    assert re.search(r"n\.log:4: META header", _convert(tmp_path, capsys, f))


def _robotlaser(start: str = "-0.785398", offset: str | None = None) -> str:
    n = 91
    lines = [f"PARAM robot_frontlaser_offset {offset} h 0"] if offset else []
    ranges = " ".join(["2.5"] * n)
    for k in range(3):
        t, x = 1.0 + k, 0.1 * k
        a = start if k == 1 else "-0.785398"
        lines.append(f"ODOM {x} 0 0 0 0 0 {t} h {t}")
        lines.append(
            f"ROBOTLASER1 0 {a} 1.570796 0.017453 30 0.01 0 {n} {ranges} "
            f"2 7 8 {x + 0.2} 0.05 0.1 {x} 0 0 0.1 0 0.5 0.3 1e6 {t} h {t}"
        )
    return "\n".join(lines) + "\n"


def test_carmen_robotlaser1_start_angle_beyond_one_turn(tmp_path, capsys):
    """A scan's start angle of 1e20 rad: beams that do not increase; refused naming the
    line."""
    f = tmp_path / "rl.clf"
    f.write_text(_robotlaser(start="99999999999999999999"))
    assert "rl.clf:4: ROBOTLASER1: start angle" in _convert(tmp_path, capsys, f)


@pytest.mark.parametrize("offset", ["1e400", "inf", "-50"])
def test_carmen_laser_offset_that_is_no_mount(tmp_path, capsys, offset):
    f = tmp_path / "off.clf"
    f.write_text(_robotlaser(offset=offset))
    assert "robot_frontlaser_offset" in _convert(tmp_path, capsys, f)


def test_ros2_metadata_with_a_list_for_a_name_or_a_type_over_two_lines(tmp_path, capsys):
    """A ROS 2 bag whose metadata.yaml gives a topic name as a list (rosbags: TypeError) or a
    message type with a line break: one line naming the bag."""
    pytest.importorskip("rosbags")
    import shutil

    from readers_helpers import write_bag

    good = tmp_path / "good"
    write_bag(good, False, n=5)
    for old, new in (
        ("name: /sonar", "name: []"),
        ("type: nav_msgs/msg/Odometry", 'type: "nav_msgs/msg/Odometry\\n| RIHS01"'),
    ):
        bag = tmp_path / "bag"
        shutil.rmtree(bag, ignore_errors=True)
        shutil.copytree(good, bag)
        meta = (bag / "metadata.yaml").read_text()
        assert old in meta
        (bag / "metadata.yaml").write_text(meta.replace(old, new))
        _convert(tmp_path, capsys, bag)


@pytest.mark.parametrize("sep", ["\\n", "\\r", "\\u2028", "\\u001c"])
def test_error_with_a_line_break_in_a_key_is_one_line(tmp_path, capsys, sep):
    """A native log whose CONFIG header names a key with a line separator in it (a flipped
    byte): the error stays on one line, the separator escaped (seen by the fuzz campaign,
    seed 1)."""
    from readers_helpers import write_native

    f = tmp_path / "k.log"
    write_native(f, n=5)
    lines = f.read_text().splitlines()
    lines[1] = lines[1].replace('"wheelbase"', f'"wheel{sep}base"', 1)
    f.write_text("\n".join(lines) + "\n")
    assert "CONFIG header: unknown key" in _convert(tmp_path, capsys, f)
