"""nirspi-pipe: near-infrared single-pixel imaging (NIR-SPI) in fog.

Simulate or replay a single-pixel camera (Hadamard-patterned 1550 nm illumination, an InGaAs
photodiode and four CW iToF lasers), reconstruct 2D images and 3D meshes, and sweep over fog,
background light and scan order with Hydra. See README.md.
"""

__version__ = "0.1.0"
