"""Serial device drivers, emulators, raw recording and replay. Never imports ``fgslam``."""
