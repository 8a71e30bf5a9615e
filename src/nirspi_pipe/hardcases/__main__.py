"""``python -m nirspi_pipe.hardcases``: :func:`nirspi_pipe.hardcases.check.main`."""

from __future__ import annotations

import sys

from nirspi_pipe.hardcases.check import main

sys.exit(main())
