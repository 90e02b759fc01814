"""maneuvers."""
