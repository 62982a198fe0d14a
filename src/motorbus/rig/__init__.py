"""An actuator test rig: step, tracking, latency and repeatability figures.

``analysis`` is the pure core (samples in, figures out); see ``docs/rig.md``.
"""
