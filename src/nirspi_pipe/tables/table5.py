"""Table 5: mesh quality (equiangle skewness) of the SFS mesh and of the final mesh, per scan
method, with 3 µm fog (5 and 15 kLux pooled). Same columns as Table 4
(:func:`nirspi_pipe.tables.table4.build_skewness`). From ``nirspi-run -m +experiment=table5``
(the fog grid of Table 3).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from nirspi_pipe.tables.table4 import build_skewness

__all__ = ["build"]


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 5 (fog) from a results frame into ``out_dir``."""
    return build_skewness(frame, out_dir, "table5", fog=True)
