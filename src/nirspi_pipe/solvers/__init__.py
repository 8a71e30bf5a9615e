"""Solvers: reconstruct an image from single-pixel measurements."""
