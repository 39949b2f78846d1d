"""Robot configuration: geometry, odometry and sensor error models, and every parameter of
every component, read from TOML (docs/design.md, 2, "One configuration path").

The default configuration (the paper's SLAMbot) ships in ``fgslam/data/robot_default.toml``;
a key it does not set takes the default written beside its field here (:func:`param`), with
its unit and meaning (``fgslam config --show`` lists them all). A user's file overrides any
subset of the keys; ``[[sonar.arrays]]`` replaces the whole list. Every error is a
:class:`ConfigError` with one line naming the file, the key and what was expected. Units are
SI; keys ending in ``_deg`` are degrees and have radian properties.
"""

from fgslam.config.fields import (
    DEFAULT_CONFIG_NAME,
    ConfigError,
    keys,
    linked,
    linked_from,
    param,
)
from fgslam.config.load import (
    MIN_BEAM_STEP,
    check_against_log,
    default_config_text,
    from_dict,
    load_config,
    override_config,
    with_options,
    with_scanmatch,
)
from fgslam.config.robot import (
    ASSOCIATION_METHODS,
    COMPONENTS,
    LINE_SPACING,
    LINE_SPAN_DEG,
    MAP_RANGE_MARGIN,
    MAP_RANGE_MIN,
    OUTLIER_SIGMAS,
    SICK_LMS_SIGMA_RANGE,
    SPREAD_SIGMAS,
    AssociationParams,
    FrontendConfig,
    FrontEndParams,
    GraphParams,
    KeyframeParams,
    LocalizeParams,
    LoopParams,
    MapParams,
    MatchParams,
    RobotConfig,
    RobotInfo,
    ScanMatchConfig,
    SegmentParams,
    frontend_thresholds,
)
from fgslam.config.sensors import (
    LaserConfig,
    Mount,
    OdometryConfig,
    SonarArrayConfig,
    SonarConfig,
)
from fgslam.config.show import (
    Entry,
    derived_values,
    entries,
)

__all__ = [
    "ASSOCIATION_METHODS",
    "COMPONENTS",
    "DEFAULT_CONFIG_NAME",
    "LINE_SPACING",
    "LINE_SPAN_DEG",
    "MAP_RANGE_MARGIN",
    "MAP_RANGE_MIN",
    "MIN_BEAM_STEP",
    "OUTLIER_SIGMAS",
    "SICK_LMS_SIGMA_RANGE",
    "SPREAD_SIGMAS",
    "AssociationParams",
    "ConfigError",
    "Entry",
    "FrontEndParams",
    "FrontendConfig",
    "GraphParams",
    "KeyframeParams",
    "LaserConfig",
    "LocalizeParams",
    "LoopParams",
    "MapParams",
    "MatchParams",
    "Mount",
    "OdometryConfig",
    "RobotConfig",
    "RobotInfo",
    "ScanMatchConfig",
    "SegmentParams",
    "SonarArrayConfig",
    "SonarConfig",
    "check_against_log",
    "default_config_text",
    "derived_values",
    "entries",
    "from_dict",
    "frontend_thresholds",
    "keys",
    "linked",
    "linked_from",
    "load_config",
    "override_config",
    "param",
    "with_options",
    "with_scanmatch",
]
