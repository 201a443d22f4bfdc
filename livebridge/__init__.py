"""livebridge: live facial motion capture to muscle contractions and animatronics."""

__version__ = "0.1.0"
