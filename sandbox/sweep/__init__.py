"""Sweeps: a level run under many perturbations, here or on a Ray cluster, and its pass rate (SPEC §10-11).

``plan`` says what runs (axes, sweep files, the ``--standard`` set),
``placement`` how a variant changes a level, ``execute`` how one run runs
and what row it gives, ``backends`` who runs them, ``table`` where the rows
go, ``report`` what they add up to, ``driver`` the whole of
``sandbox sweep``.
"""

from sandbox.sweep.driver import SweepOptions, run_sweep
from sandbox.sweep.plan import SweepError, grid_variants, load_sweep, parse_sweep, sample_variants, standard_variants
from sandbox.sweep.report import wilson, write_reports

__all__ = ["SweepError", "SweepOptions", "grid_variants", "load_sweep", "parse_sweep", "run_sweep",
           "sample_variants", "standard_variants", "wilson", "write_reports"]
