"""Hydra's plugin scan imports ``hydra_plugins.nirspi_pipe_sweeper`` while ``nirspi_pipe.app.configs``
is being imported (its import registers the schemas and runs the scan). In a non-editable install,
where ``hydra_plugins`` is a real package, a module-level import of ``app.entry`` (which imports
``app.configs``) from the launcher or the sweeper is therefore an import circle: every ``nirspi-run``
then printed Hydra's "Error importing 'hydra_plugins.nirspi_pipe_sweeper' ... partially initialized
module" warning (CI's fresh clone, issue 41's per-job gate). An editable install hides it (Hydra's
scan does not see the editable ``hydra_plugins``), so this checks the invariant that rules it out."""

from __future__ import annotations

import json
import subprocess
import sys


def test_the_plugin_package_does_not_load_the_config_layer() -> None:
    code = (
        "import json, sys; import hydra_plugins.nirspi_pipe_sweeper; "
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith('nirspi_pipe.app'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    loaded = set(json.loads(out.stdout.strip().splitlines()[-1]))
    assert "nirspi_pipe.app.sweeper" in loaded and "nirspi_pipe.app.launcher" in loaded
    assert not loaded & {"nirspi_pipe.app.entry", "nirspi_pipe.app.configs"}, loaded
