"""Re-processing recorded takes in batch: reconstruction and/or solve of many takes, on a Dask cluster.

:mod:`.jobs` plans the work (one :class:`~.jobs.TakeJob` per take, checked up front), :mod:`.reprocess` is the
serial work on one take (the live path's reconstruction and solver, or the offline solve), :mod:`.outputs`
writes its results, :mod:`.cluster` runs the jobs on a Dask ``distributed`` cluster (an optional extra:
``pip install 'livebridge[cluster]'``; imported only there).
"""
