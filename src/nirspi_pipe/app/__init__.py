"""nirspi-pipe's Hydra application: the layer above the runner.

The runner (:mod:`nirspi_pipe.pipeline`, :mod:`nirspi_pipe.execute`, :mod:`nirspi_pipe.instantiate`,
:mod:`nirspi_pipe.records` and the stage packages) takes a resolved configuration as plain data
and imports nothing of Hydra or OmegaConf. This package composes those configurations and
hands them down:

- :mod:`~nirspi_pipe.app.cli`: ``nirspi-run`` and ``nirspi-collect``;
- :mod:`~nirspi_pipe.app.validate`: one-line errors before anything is built;
- :mod:`~nirspi_pipe.app.configs`: the config catalogue and the options' generated schemas;
- :mod:`~nirspi_pipe.app.sweeper`, :mod:`~nirspi_pipe.app.launcher`,
  :mod:`~nirspi_pipe.app.launchsettings`, :mod:`~nirspi_pipe.app.registration`: the resumable
  sweeper and the forking launcher (Hydra plugins, in ``hydra_plugins.nirspi_pipe_sweeper``);
- :mod:`~nirspi_pipe.app.jobs`: one crash-isolated sweep job, and ``execute_job`` for a
  composed config;
- :mod:`~nirspi_pipe.app.results`: records to pandas tables, the multirun callback;
- :mod:`~nirspi_pipe.app.plugins`, :mod:`~nirspi_pipe.app.helptext`: plugin discovery, ``--help``;
- :mod:`~nirspi_pipe.app.api`: the Python API (``nirspi_pipe.run`` and friends);
- :mod:`~nirspi_pipe.app.devicecli`: ``nirspi-device-emulator``'s command line.

The direction is enforced by ``tests/test_architecture.py``: nothing outside this package (and
``hydra_plugins``) reaches Hydra, OmegaConf or this package, even through other modules.
"""
