"""How DEM runs are executed and kept: the SQLite store (``store``), executors in-process or on dask (``executor``), the batched draw down evaluation (``dem``)."""
