"""Simulated devices: performer, camera rig, servo buses (livebridge.simulators).

The URL schemes this package implements, as plain data for :mod:`livebridge.devices.registry`, like the
real drivers declare theirs (nothing is imported until a scheme is opened). A simulated bus is driven by
the real driver, so it has that driver's facts.
"""

CAMERA_SCHEMES = {
    "sim": "livebridge.simulators.sim_url:open_url",
}

# scheme -> (opener, the facts of the real driver that drives the simulated bus)
BUS_SCHEMES = {
    "simdynamixel": ("livebridge.simulators.dynamixel_bus:open_url", "livebridge.drivers.dynamixel:FACTS"),
    "simmaestro": ("livebridge.simulators.maestro_bus:open_url", "livebridge.drivers.maestro:FACTS"),
    "simssc32": ("livebridge.simulators.ssc32_bus:open_url", "livebridge.drivers.ssc32:FACTS"),
}
