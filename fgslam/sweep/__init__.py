"""Sweeps: many runs (logs, simulated seeds, backends, sensor modes, any configuration key)
on Dask, resumable, with a report (``fgslam sweep``; docs/sweeps.md)."""

from fgslam.sweep.engine import SweepRun, run_sweep, sweep_function
from fgslam.sweep.report import write_report
from fgslam.sweep.spec import Cell, SweepError, SweepSpec, load_spec, spec_from_dict

__all__ = [
    "Cell",
    "SweepError",
    "SweepRun",
    "SweepSpec",
    "load_spec",
    "run_sweep",
    "spec_from_dict",
    "sweep_function",
    "write_report",
]
