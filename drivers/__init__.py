"""Camera sources and servo buses for real hardware (livebridge.drivers)."""
