"""Dataset acquisition for a run: the simulator's dataset is prepared (or resumed, or checked)
and real data is converted on first use; either way with every map variant the config asks for
(``data.map_variants`` / ``dataset.convert.map_variants``) plus the run's own ``map``, and for
an NM model (``model.variant=nm``) the OSM class rasters its neural map reads."""

from __future__ import annotations

import os

from seglocnet_jax.app.schema import ExperimentConfig
from seglocnet_jax.data import manifest as mf
from seglocnet_jax.data.simulated import prepare as prepare_lib


def prepare_dataset(cfg: ExperimentConfig) -> str:
    """Prepares what is missing and returns the dataset directory (progress shown)."""
    if cfg.dataset is not None:
        return _prepare_real(cfg)
    dataset_dir, _ = prepare_lib.prepare_for_training(
        cfg.data, cfg.map, osm_classes=reads_osm_classes(cfg)
    )
    return dataset_dir


def reads_osm_classes(cfg: ExperimentConfig) -> bool:
    """Whether the run's model reads the OSM class rasters (the neural map's ``nm_tile``)."""
    return cfg.model.variant == "nm"


def _prepare_real(cfg: ExperimentConfig) -> str:
    from seglocnet_jax.data.real import convert as real_convert

    reader_cls, reader_cfg, convert_cfg = real_convert.parse_tree(cfg.dataset)
    dataset_dir = os.path.join(convert_cfg.root, convert_cfg.name)
    if os.path.isfile(mf.manifest_path(dataset_dir)):
        mf.read_manifest(dataset_dir)  # an old or edited manifest is an error naming it
        if prepare_lib.dataset_ready(dataset_dir, [cfg.map], osm_classes=reads_osm_classes(cfg)):
            return dataset_dir
    dataroot = reader_cfg.dataroot
    if not os.path.isdir(dataroot):
        raise FileNotFoundError(
            f"experiment {cfg.name!r}: data directory {dataroot!r} (dataset.reader.dataroot) "
            f"does not exist and {dataset_dir!r} holds no converted dataset with map variant "
            f"{cfg.map.name!r}"
            + (" and the OSM class rasters of an NM model" if reads_osm_classes(cfg) else "")
            + f". Put the {cfg.dataset['source']} data there or pass "
            "dataset.reader.dataroot=PATH; the first run converts it (README, 'Using real data')"
        )
    dataset_dir, _ = real_convert.convert_for_training(
        reader_cls(reader_cfg), convert_cfg, cfg.map, osm_classes=reads_osm_classes(cfg)
    )
    return dataset_dir
