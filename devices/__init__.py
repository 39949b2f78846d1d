"""Serial device drivers, emulators, raw recording and replay. Never imports ``fgslam``.

- ``devices.sick``: SICK PLS telegrams (CRC, streaming decoder, B0 values) and driver
- ``devices.sonar``, ``devices.odometry``: the framed protocol's devices (``devices.frames``)
- ``devices.driver``: the serial port, recording hooks, ``DeviceRunner`` (thread, reconnect)
- ``devices.clock``: log clock with a speed factor, device-time mapping
- ``devices.raw``, ``devices.replay``: crash-safe raw recordings and their replay
- ``devices.emulators``: the three devices on pseudo-terminals
- ``devices.pty_emulator``: what every emulator shares: the pty, its link, the thread, faults
- ``devices.playback``: the thread that feeds the emulators their measurements at their times

Protocols and formats: ``docs/devices.md``. fgslam events: ``fgslam.online.ports``.
"""
