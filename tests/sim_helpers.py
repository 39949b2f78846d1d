"""Groups of the simulator's true errors switched off, by name, for tests that want part of
the robot exact: keywords of :class:`fgslam.sim.sensors.SimParams`
(``SimParams(**EXACT_WHEELS, **NO_LASER_BIAS)``)."""

from __future__ import annotations

# the real wheel radii and wheelbase are the nominal ones
EXACT_WHEELS = {"radius_error_right": 0.0, "radius_error_left": 0.0, "wheelbase_error": 0.0}
# the laser's ranges carry their random error only (no offset, no error growing with range)
NO_LASER_BIAS = {"laser_sys_offset": 0.0, "laser_sys_per_metre": 0.0}
# no mixed pixels, no misclassified sonar echoes, no phantom echoes
NO_CLUTTER = {"mixed_pixel_prob": 0.0, "misclass_prob": 0.0, "phantom_prob": 0.0}
