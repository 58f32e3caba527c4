"""The paper's Monte Carlo accuracy/runtime study (Figs. 4 and 5), sharded over devices.

For a model, a batch of random sinusoidal maneuvers, a duration (10 s, 10 min), a set of
integrators and resolutions (total number of steps N): the position error against a
high-accuracy reference (final and max over time), the runtime per trajectory (batched, after
compilation, median of repeats) and the failure rate. Split by concern:

* :mod:`._config`: the methods, the models and :class:`StudyConfig`;
* :mod:`._maneuvers`: reproducible random maneuvers;
* :mod:`._batch`: batched rollouts (:func:`ldap_jax.simulate` over a sharded batch) and the reference;
* :mod:`._summary`: a point's rollouts reduced to its row on the devices;
* :mod:`._chunks`: each point's row kept on disk, so that a stopped study resumes;
* :mod:`._run`: the study loop and the runtime ratios;
* :mod:`._report`: CSV, markdown tables and figures.

The study runs the same in one process or in several (``jax.distributed.initialize``; see
``scripts/sweep.py`` and :mod:`ldap_jax.launch`): the batch is split over the devices of every
process, each process samples and runs its own devices' maneuvers, and only each point's numbers
come back to the host.

Example:
    >>> rows = run_study(StudyConfig(models=("snakeboard",), durations=(10.0,), runs=8,
    ...                              methods=("rdp", "rk2"), resolutions=(100, 200)))
    >>> write_csv(rows, "results/sweep.csv")
"""

from ._batch import batch_rollout as batch_rollout
from ._batch import device_mesh as device_mesh
from ._batch import reference_batch as reference_batch
from ._batch import rollout_nodes as rollout_nodes
from ._batch import shard_batch as shard_batch
from ._chunks import ChunkStore as ChunkStore
from ._config import CSV_COLUMNS as CSV_COLUMNS
from ._config import METHODS as METHODS
from ._config import MODELS as MODELS
from ._config import StudyConfig as StudyConfig
from ._config import make_integrator as make_integrator
from ._maneuvers import global_maneuvers as global_maneuvers
from ._maneuvers import sample_maneuvers as sample_maneuvers
from ._report import format_table as format_table
from ._report import plot_study as plot_study
from ._report import read_csv as read_csv
from ._report import write_csv as write_csv
from ._run import position_errors as position_errors
from ._run import run_study as run_study
from ._run import runtime_ratios as runtime_ratios
from ._run import study_maneuvers as study_maneuvers
from ._summary import point_statistics as point_statistics
