"""Converts the Argoverse 2 sensor dataset (one city's logs) into a prepared dataset.

    python data_prep/convert_argoverse.py dataset.reader.dataroot=/data/av2/sensor \
        +dataset.convert.osm.MIA=/data/osm/miami.osm.pbf           # argo_mia (default preset)
    python data_prep/convert_argoverse.py --preset argo_pit \
        dataset.reader.dataroot=/data/av2/sensor +dataset.convert.osm.PIT=/data/osm/pit.osm.pbf

Config: ``conf/dataset/<preset>.yaml`` (``argo_mia`` / ``argo_pit``) plus Hydra overrides. The
logic lives in ``seglocnet_jax.data.real.convert``; an interrupted run resumes where it stopped.
"""

import sys

from hydra import compose, initialize_config_dir

from seglocnet_jax.app import hydra_glue
from seglocnet_jax.data.real.convert import convert, from_tree, summary


def main(argv: list[str]) -> None:
    preset = "argo_mia"
    if argv[:1] == ["--preset"]:
        preset, argv = argv[1], argv[2:]
    with initialize_config_dir(config_dir=hydra_glue.conf_dir(), version_base="1.3"):
        tree = hydra_glue.to_tree(compose(config_name=f"dataset/{preset}", overrides=argv))
    reader, cfg = from_tree(tree["dataset"])  # a group file sits under its group name
    dataset_dir = convert(reader, cfg)
    print(summary(dataset_dir))


if __name__ == "__main__":
    main(sys.argv[1:])
