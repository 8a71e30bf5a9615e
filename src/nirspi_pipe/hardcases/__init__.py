"""The hard-case catalogue: inputs at the edges of every range, with the bounds each must meet.

    python -m nirspi_pipe.hardcases                   # run every case, print one line per case
    python -m nirspi_pipe.hardcases --write-docs      # ... and write docs/hardcases.md
    python -m nirspi_pipe.hardcases ID [ID ...]       # only these cases

The cases live in one data file, ``nirspi_pipe/data/hardcases.yaml`` (issue 40). Each has an
``id``, ``what`` it probes, how it runs and what it must give:

* ``run: [override, ...]``: one :func:`nirspi_pipe.run` of ``nirspi-run`` overrides, in this
  process; or ``call: NAME`` with ``args``: one of the probes in :data:`PROBES` (a stage called
  directly, a run repeated, a run under other BLAS threads, a run with one input moved by 1e-9);
* ``expect``: ``ok``; ``{refused: KEY}`` (a :class:`ValueError` with one line that starts with the
  key the user set); or ``{failed: TEXT}`` (a one-line :class:`~nirspi_pipe.errors.NirspiError`
  holding ``TEXT``, for a stage called on input it cannot use);
* ``bounds``: ``"LHS OP RHS"`` with OP one of ``<= >= < > ==``; names are record values
  (``metrics.psnr``, ``derived.snr_db``, ``info.fusion.anchors_used``) or a probe's results
  (``max_abs_diff``); ``abs``, ``min`` and ``max`` may be used. The measured value is the LHS;
* ``left_out``: record values the case allows :func:`nirspi_pipe.finite.drop_nonfinite` to
  remove (default none);
* ``pending``: why the case's ideal bound does not hold, with what was measured (the test suite
  expects it to fail: ``xfail(strict=True)``), or ``note``: why a bound is what it is.

Every ``run`` case that should succeed is also checked for: no ``RuntimeWarning``; nothing left
out of the record unless ``left_out`` names it; every metric finite; every SSIM in [-1, 1];
every RMSE >= 0. ``tests/test_hardcases.py`` runs every case (parametrized by id).

The package's modules (issue 42 item 5): :mod:`.catalogue` (the cases, loaded and their bounds
checked), :mod:`.probes` (the ``call:`` probes and one run's values), :mod:`.check` (one case run
and checked; the command line, :func:`~nirspi_pipe.hardcases.check.main`) and :mod:`.render`
(docs/hardcases.md).
"""
