"""mesh stage implementations."""
