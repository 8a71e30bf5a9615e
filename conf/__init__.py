"""nirspi-pipe's config groups. Importing the package (Hydra does, to read it) registers the
schemas of its options: the defaults of each option's ``_target_`` (``nirspi_pipe.app.configs``)."""

from nirspi_pipe.app.configs import register_schemas

register_schemas(__name__)
