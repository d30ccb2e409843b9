"""HIL sweeps: a grid of in-process HIL scenarios on Dask distributed (``planer sweep``).

The package, by job: :mod:`planer.sweep.design` (the sweep file and its grid; pure),
:mod:`planer.sweep.point` (one run: configurations checked by the project's loaders, the
in-process HIL on simulated time, its outcome row), :mod:`planer.sweep.driver` (Dask
``LocalCluster`` or an existing scheduler, ``results.csv`` written as runs finish, progress
bar), :mod:`planer.sweep.plots` (the outcome over the grid). Dask is imported only when a
sweep runs on it.
"""

from planer.sweep.design import Point, Sweep, expand, grid_combinations, load_sweep, sweep_from_dict
from planer.sweep.driver import ProgressBar, ResultsWriter, read_results, run_sweep
from planer.sweep.plots import outcome_figure, save_plots
from planer.sweep.point import OUTCOME_COLUMNS, Job, base_values, make_job, prepare, run_job

__all__ = [
    "OUTCOME_COLUMNS",
    "Job",
    "Point",
    "ProgressBar",
    "ResultsWriter",
    "Sweep",
    "base_values",
    "expand",
    "grid_combinations",
    "load_sweep",
    "make_job",
    "outcome_figure",
    "prepare",
    "read_results",
    "run_job",
    "run_sweep",
    "save_plots",
    "sweep_from_dict",
]
