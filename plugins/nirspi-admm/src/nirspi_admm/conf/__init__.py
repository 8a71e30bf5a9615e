"""Hydra config folder of the nirspi-admm plugin (``<group>/<option>.yaml``)."""
