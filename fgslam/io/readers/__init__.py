"""Readers of foreign logs into fgslam's event stream (docs/readers.md): CARMEN
(:mod:`~fgslam.io.readers.carmen`), ROS 1 / ROS 2 bags (:mod:`~fgslam.io.readers.ros`, needs
``rosbags``) and Victoria Park (:mod:`~fgslam.io.readers.victoria`), with the rules they share
(:mod:`~fgslam.io.readers.common`, :mod:`~fgslam.io.readers.sanity`,
:mod:`~fgslam.io.readers.plausibility`): the one reader interface and its problems
(:mod:`~fgslam.io.readers.source`), odometry given as poses (:mod:`~fgslam.io.readers.odometry`).
:func:`fgslam.io.formats.open_log` picks the reader.
"""
