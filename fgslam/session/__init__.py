"""Map reuse (docs/sessions.md): a run saved as a session (:mod:`~fgslam.session.store`), its
occupancy grid in the ROS map_server format (:mod:`~fgslam.session.grid`), and localization
on a saved session (:mod:`~fgslam.session.localize`)."""

from fgslam.session.store import FORMAT_VERSION, Session, SessionError, load_session, save_session

__all__ = ["FORMAT_VERSION", "Session", "SessionError", "load_session", "save_session"]
