"""reach layer."""
