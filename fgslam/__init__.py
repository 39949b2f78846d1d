"""fgslam: laser + advanced sonar SLAM as a GTSAM factor graph, with the paper's EKF as a mode."""

__version__ = "0.1.0"
