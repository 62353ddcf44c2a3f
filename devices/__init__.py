"""Device plugins: the per-kind contract (base), the registry, mock devices and real drivers.

Simulation code lives in ``devices/sim`` and is never imported by a real driver.
"""
