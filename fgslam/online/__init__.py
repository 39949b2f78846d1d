"""Online SLAM on live devices: serial ports, one process per device, the online loop.

- :mod:`fgslam.online.ports`: opening serial ports (or emulators) and decoding their frames;
- :mod:`fgslam.online.device_process`: one reader process per device, feeding a queue;
- :mod:`fgslam.online.loop`: the online loop, merging the devices' events in time order into
  the same SLAM step as offline runs.
"""
