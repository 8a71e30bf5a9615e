"""scene stage implementations."""
