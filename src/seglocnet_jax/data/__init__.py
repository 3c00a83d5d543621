"""Data. This level is the dataset format that every producer writes and the loader reads: the
sample / batch schema (:mod:`.schema`), records and shards (:mod:`.records`), the manifest
(:mod:`.manifest`), each record's seeded prior (:mod:`.priors`), the writer (:mod:`.writer`), map
variants (:mod:`.variants`) and the grain loader (``loader.make_loader``: one split as
fixed-shape NumPy batches).

Producers: :mod:`.simulated` (``simulated.prepare.prepare(cfg) -> dataset_dir`` builds or resumes
the simulator's dataset) and :mod:`.real` (nuScenes and Argoverse 2 converted, with OSM maps
aligned to them). Neither imports the other; this level imports neither.
"""
