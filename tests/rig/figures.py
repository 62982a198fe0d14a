"""The figures a rig run writes per actuator, for the tests."""

#: Every figure ``DeviceResult.figures`` writes (docs/rig.md defines each).
WRITTEN = (
    "step.dead_time_ms", "step.rise_time_ms", "step.speed_units_per_s",
    "step.mean_speed_units_per_s", "step.overshoot_pct", "step.settling_time_ms",
    "step.steady_state_error", "step.peak_current_ma", "step.peak_force_g",
    "track.rms_error", "track.max_error", "track.lag_ms",
    "latency.p50_ms", "latency.p99_ms", "latency.max_ms",
    "repeat.spread", "repeat.backlash", "repeat.std_below", "repeat.std_above",
)  # fmt: skip
