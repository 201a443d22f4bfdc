"""Simulated devices: performer, camera rig, servo buses (livebridge.simulators)."""
