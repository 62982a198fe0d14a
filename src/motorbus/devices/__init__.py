"""motorbus.devices."""
