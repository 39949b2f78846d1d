"""Inputs and outputs: every log format read into one event stream, and files written safely.

- :mod:`fgslam.io.readers`: foreign logs (CARMEN, ROS bags, Victoria Park) and the format sniffer;
- :mod:`fgslam.io.formats`: which reader reads a file (``open_log``: every format behind one
  interface, :class:`fgslam.io.readers.source.LogSource`);
- :mod:`fgslam.io.logfile`: fgslam's own log format: the reader (the writer in
  :mod:`fgslam.io.logwriter`, one event per line in :mod:`fgslam.io.logrecords`);
- :mod:`fgslam.io.ordering`: merging sensor streams into one time-ordered stream;
- :mod:`fgslam.io.safeio`: atomic writes and the guard that keeps one failed output from losing
  the others.

This layer sits above the vocabulary (``fgslam.config``, ``fgslam.events``, ``fgslam.errors``),
the scan matcher and the front end, and below everything that runs SLAM (docs/design.md, 1).
"""
