"""Real datasets converted into the dataset format: the readers (:mod:`.nuscenes`,
:mod:`.argoverse`) and their common frame loop (:mod:`.common`), the conversion
(:mod:`.convert`: ``convert(cfg) -> dataset_dir``), and the HD / SD map rasters of each city
(:mod:`.map_rasters`) with the OSM alignment they need (what an alignment is:
:mod:`.alignment`; its windows: :mod:`.align_windows`; the fit: :mod:`.align_fit`; its checks:
:mod:`.align_checks`)."""
