"""Measurement models and GTSAM factors: pure math, no I/O, never imports ``fgslam``.

Each landmark kind has one prediction function with analytic Jacobians, shared by the EKF
and by the factor graph (``line``, ``corner``, ``point``); ``odometry`` holds the paper's
odometry model and its preintegration; ``sensor_models`` the measurement covariances.
"""
