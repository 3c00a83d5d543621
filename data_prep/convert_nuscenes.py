"""Converts nuScenes into a prepared dataset: ArrayRecord shards + HD/SD rasters per map.

    python data_prep/convert_nuscenes.py dataset.reader.dataroot=/data/nuscenes \
        +dataset.convert.osm.boston-seaport=/data/osm/boston.osm.pbf \
        +dataset.convert.osm.singapore-onenorth=/data/osm/singapore.osm.pbf ...
    python data_prep/convert_nuscenes.py dataset.reader.dataroot=/data/nuscenes \
        dataset.reader.version=v1.0-mini dataset.convert.name=nuscenes_mini \
        'dataset.convert.splits={train: mini_train, val: mini_val}' ...

Config: ``conf/dataset/nuscenes.yaml`` (Hydra overrides on the command line). The logic lives in
``seglocnet_jax.data.real.convert``; an interrupted run resumes where it stopped.
"""

import sys

from hydra import compose, initialize_config_dir

from seglocnet_jax.app import hydra_glue
from seglocnet_jax.data.real.convert import convert, from_tree, summary


def main(argv: list[str]) -> None:
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        tree = hydra_glue.to_tree(compose(config_name="dataset/nuscenes", overrides=argv))
    reader, cfg = from_tree(tree["dataset"])  # a group file sits under its group name
    dataset_dir = convert(reader, cfg)
    print(summary(dataset_dir))


if __name__ == "__main__":
    main(sys.argv[1:])
