"""Data: the sample/batch schema, ArrayRecord shards, offline preparation and the grain loader.

``prepare.prepare(cfg) -> dataset_dir`` builds (or resumes) a dataset; ``loader.make_loader``
reads one split of it as fixed-shape NumPy batches.
"""
