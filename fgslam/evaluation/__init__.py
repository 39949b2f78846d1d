"""Judging and drawing a run: trajectory metrics, dense trajectories, plots, calibration fits.

- :mod:`fgslam.evaluation.metrics`: ATE, RPE, the relations benchmark, NEES, TUM files;
- :mod:`fgslam.evaluation.dense`: every scan's pose from keyframes and odometry;
- :mod:`fgslam.evaluation.reference`: reference trajectories read from any supported file;
- :mod:`fgslam.evaluation.plotting`: maps, trajectories and worlds in matplotlib;
- :mod:`fgslam.evaluation.calibrate`: odometry noise fitted against a reference.

Imports the vocabulary, ``fgslam.io`` and ``fgslam.sim``; used by ``fgslam.slam`` (outputs),
``fgslam.online`` and ``fgslam.cli``.
"""
