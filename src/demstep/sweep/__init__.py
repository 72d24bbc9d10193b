"""Parameter sweeps of a case on Dask, and :func:`dask_map`, the helper they run on.

Parts: :mod:`~demstep.sweep.cluster` (Dask), :mod:`~demstep.sweep.plan` (keys, values,
runs, ids), :mod:`~demstep.sweep.summary` (one run on a worker, summary.csv and .png)
and :mod:`~demstep.sweep.driver` (:func:`run_sweep`).

A sweep runs one case many times with some keys changed (``demstep sweep``)::

    demstep sweep case.toml --param contact.mu=0.1,0.2,0.3 \\
        --param timestep.alpha=0.05,0.35,0.4 --out sweep/

Keys are dotted paths into the case schema (:mod:`demstep.case`): ``contact.mu``,
``timestep.alpha``, ``stages[1].mu``, ``stages[0].walls."y+".velocity``. Values are TOML
values (``0.1``, ``1e4``, ``true``, ``"hertz"``, ``[0.0, -9.81]``); text that is not
TOML is taken as a string. The runs are the cartesian product of the values, or the
rows of a CSV file (header: the keys) or the ``[[runs]]`` tables of a TOML file (both
combined with any ``--param``). Every run's case is validated before anything is
written.

The output folder holds::

    sweep.json       the sweep: case, keys, runs (id and overrides), options
    case.toml        a copy of the case file as given
    summary.csv      one row per run (see SUMMARY_COLUMNS), rewritten as runs finish
    summary.png      max energy error and peak value against the first key
    runs/<run-id>/   each run's folder, written by demstep.runner.run_case

A run id is made of the overrides, ``contact.mu=0.1__timestep.alpha=0.05`` (index
brackets become dots, characters other than letters, digits and ``._+=-`` become
``_``; a short hash is appended when it is longer than :data:`MAX_ID_LENGTH`).
Running the same sweep into the same folder again skips every run whose ``run.json``
says completed, diverged or energy_stop for the same resolved case and
``--max-steps`` (resume), and runs the others (failed, unfinished, changed) afresh.

The output folder is locked while a sweep writes into it (a second sweep into the
same folder is refused), and each run's folder while its run writes. While the
cluster has no worker the sweep says so (with the number of runs pending); after
``worker_timeout`` seconds without one it gives up the runs not done, marked
'unfinished' in summary.csv (run the sweep again to resume them).

Execution (:func:`dask_client`): a ``distributed.LocalCluster`` of ``workers`` worker
processes of one thread each, or an existing cluster given by its scheduler address.
Each task runs numba with one thread (:data:`WORKER_ENV` on a local cluster and
``numba.set_num_threads(1)`` in the task): the worker processes already share the
cores. Each run writes its own folder on the worker, so with a remote cluster the
output folder must be on a file system every worker and the client share.
"""


from demstep.sweep.cluster import (
    WORKER_ENV, WORKER_TIMEOUT, TaskResult, dask_client, dask_map, map_on_client, worker_info,
)
from demstep.sweep.driver import SweepResult, mark_unfinished, run_sweep
from demstep.sweep.plan import (
    SweepPlan, combine_runs, key_text, parse_key, parse_param, parse_value, plan_sweep,
    read_runs_file, run_id, set_key, split_values, value_text,
)
from demstep.sweep.summary import RunTask, run_task, summarize_run, write_summary

__all__ = ["RunTask", "SweepPlan", "SweepResult", "TaskResult", "WORKER_ENV", "WORKER_TIMEOUT",
           "combine_runs", "dask_client", "dask_map", "key_text", "map_on_client",
           "mark_unfinished", "parse_key", "parse_param", "parse_value", "plan_sweep",
           "read_runs_file", "run_id", "run_sweep", "run_task", "set_key", "split_values",
           "summarize_run", "value_text", "worker_info", "write_summary"]
