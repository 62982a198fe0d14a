"""motorbus.cli."""
