"""``nirspi-device-emulator``'s console script: the device emulator with the config layer's
scene renderer (the emulator itself, in :mod:`nirspi_pipe.device.emulator`, composes no config)."""

from __future__ import annotations

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    """``nirspi-device-emulator``: serve a simulated scene option on 127.0.0.1 (prints the port)."""
    from nirspi_pipe.app.configs import render_scene  # start-up: loads hydra and omegaconf (1891 ms here)
    from nirspi_pipe.device.emulator import main as serve  # start-up: loads numpy (802 ms here)

    serve(argv, render_scene=render_scene)
