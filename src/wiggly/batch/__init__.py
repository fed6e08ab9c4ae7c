"""Many shots at once: scene files or a sweep, on local worker processes or a Ray cluster.

    inputs -> shots (scene files, expanded sweeps) -> distinct bodies, each prepared once
           -> shots on workers (a process per core, or Ray) -> one folder per shot
           -> summary.csv / summary.json, contact sheets

* :mod:`~wiggly.batch.sweep` -- the sweep format (``docs/sweep-format.md``): one base
  scene, grids and random draws over its parameters, checked with the scene format's
  validation framework;
* :mod:`~wiggly.batch.shots` -- the shots, their folder names and content keys;
* :mod:`~wiggly.batch.worker` -- what runs in a worker: a body prepared, a shot solved on it;
* :mod:`~wiggly.batch.backends` -- local worker processes, or a Ray cluster;
* :mod:`~wiggly.batch.driver` -- :func:`run`: the driver;
* :mod:`~wiggly.batch.summary` -- the summary and the contact sheets.
"""

from wiggly.batch.driver import run
from wiggly.batch.sweep import Sweep, load_sweep, sweep_schema

__all__ = ["Sweep", "load_sweep", "run", "sweep_schema"]
