"""SegLocNet in JAX/Flax: GNSS-free localization by BEV segmentation matched to HD/SD maps."""

__version__ = "0.1.0"
