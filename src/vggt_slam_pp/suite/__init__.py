"""``vggt-slam-pp evaluate SUITE.yaml``: datasets x configurations x seeds, resumable runs (a process
pool or Ray), and the paper-style tables and plots (docs/evaluation.md, "Suites")."""

from vggt_slam_pp.suite.runner import run_suite, run_task
from vggt_slam_pp.suite.spec import SuiteSpec, Task, expand, load_suite
from vggt_slam_pp.suite.tables import aggregate, write_plots, write_tables

__all__ = ["SuiteSpec", "Task", "load_suite", "expand", "run_suite", "run_task", "aggregate", "write_tables",
           "write_plots"]
