"""The values each enumerated configuration key may take: one home for the configuration's
checks, the command line's choices and the experiments' (no heavy imports, so that
``fgslam --help`` stays fast)."""

from __future__ import annotations

SCANMATCH_CHOICES = {
    "odometry": ("wheels", "scan", "both"),
    "keyframes": ("motion", "every-scan"),
    "loop_closures": ("on", "off"),
}
CALIBRATION_CHOICES = ("off", "wheels")
LASER_CALIBRATION_CHOICES = ("off", "offset", "range")
CORNER_CHOICES = ("with-lines", "replace-lines", "off")
POINTS_FROM_CHOICES = ("any-echo", "unfused-echoes")
LINE_END_CHOICES = ("as-segmented", "at-vertex")
TIME_REGISTRATION_CHOICES = ("per-feature", "per-scan")
SONAR_TIMING_CHOICES = ("scan-frame", "own-time")
SONAR_CALIBRATION_CHOICES = ("off", "sound")
ROBUST_CHOICES = ("none", "huber", "cauchy", "dcs")  # factors.noise.ROBUST_KERNELS
FACTORIZATION_CHOICES = ("QR", "CHOLESKY")
LOCALIZE_MOTION_CHOICES = ("wheels", "fused", "scan")

# (section, key) -> choices
CHOICES = {
    **{("scanmatch", key): choices for key, choices in SCANMATCH_CHOICES.items()},
    ("frontend", "corners"): CORNER_CHOICES,
    ("frontend", "points_from"): POINTS_FROM_CHOICES,
    ("frontend", "line_ends"): LINE_END_CHOICES,
    ("sonar", "timing"): SONAR_TIMING_CHOICES,
    ("sonar", "calibration"): SONAR_CALIBRATION_CHOICES,
    ("odometry", "calibration"): CALIBRATION_CHOICES,
    ("laser", "calibration"): LASER_CALIBRATION_CHOICES,
    ("laser", "time_registration"): TIME_REGISTRATION_CHOICES,
    ("graph", "robust"): ROBUST_CHOICES,
    ("graph", "factorization"): FACTORIZATION_CHOICES,
    ("localize", "motion"): LOCALIZE_MOTION_CHOICES,
}
