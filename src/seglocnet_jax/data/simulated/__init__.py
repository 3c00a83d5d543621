"""The simulator's dataset: its config (:mod:`.config`), the frames of each split (:mod:`.splits`,
:mod:`.planning`, whole drives in :mod:`.drives`), the simulator as their producer
(:mod:`.source`) and the preparation that renders and writes them (:mod:`.prepare`:
``prepare(cfg) -> dataset_dir``)."""
