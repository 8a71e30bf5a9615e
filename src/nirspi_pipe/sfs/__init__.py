"""sfs stage implementations."""
