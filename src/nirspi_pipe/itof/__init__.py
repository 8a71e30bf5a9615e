"""itof stage implementations: the four CW iToF reference lasers (paper §3, Table 1)."""

from nirspi_pipe.itof.cw4 import ContinuousWave4, demodulate_4phase, laser_directions

__all__ = ["ContinuousWave4", "demodulate_4phase", "laser_directions"]
