"""physics stage implementations."""
