"""The load benchmark's parts (``python -m benchmarks.bench_load`` runs them): the served scene
and its walks (``scenes``, ``ground``), the servers (``servers``), the walkers (``walkers``),
the hostile client (``hostile``), the frames' image error (``frames``), the numbers of a run
(``summary``) and the report (``report``)."""
