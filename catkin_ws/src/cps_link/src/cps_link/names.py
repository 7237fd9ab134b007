"""cps_link's graph names (resolved names; the bridge's topic table is config/bridge.yaml)."""

# TwistStamped probes sent twin -> robots in the bridge's command class, the class teleop rides in:
# their latency, measured on the robots' side, is the teleop command latency.
COMMAND_PROBE = "/tissue/command_probe"
COMMAND_PROBE_RATE_HZ = 10.0
