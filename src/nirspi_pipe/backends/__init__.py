"""Stages with more than one back end, declared in one place (issue 27: one parity harness).

Each :class:`Family` names a reference back end and its alternatives, the fixtures every back end
runs on, a comparison of two outputs as named discrepancies, and a bound on each discrepancy with
where that bound comes from. ``tests/test_parity.py`` runs every alternative of every family
against the reference on every fixture and checks every bound; a back end that cannot run here
(no OpenCL device, torch or pymeshlab not installed) is skipped with the reason
:meth:`~.harness.Backend.unavailable` gives.

Plain data and functions: no configuration system, and every back end is imported only when it is
asked whether it is available or run, so importing this module costs nothing.

Adding a back end: add a :class:`~.harness.Backend` to its family's ``alternatives`` (or a new
:class:`~.harness.Family` to :data:`~.registry.REGISTRY`), with its bounds measured on the family's fixtures.

The package's modules (issue 42 item 5): :mod:`.harness` (``Backend``, ``Tolerance``, ``Family``,
``violations``), one module per family (:mod:`.sfs`, :mod:`.omp`, :mod:`.fsrcnn`, :mod:`.remesh`: its
fixtures, back ends, comparison and bounds) and :mod:`.registry` (``REGISTRY``, every family by name).
"""
