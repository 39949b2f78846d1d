"""SLAM: map management shared by three backends (the paper's EKF, iSAM2, batch smoothing)."""
