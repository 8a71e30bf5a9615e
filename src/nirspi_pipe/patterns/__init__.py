"""Hadamard/Walsh basis, fast transforms and scan orders."""
