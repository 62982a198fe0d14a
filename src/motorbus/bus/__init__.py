"""motorbus.bus."""
