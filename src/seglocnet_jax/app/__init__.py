"""The app floor: experiment schema, dataset acquisition, the train and evaluate runs, Hydra glue
and previews. Entry points (``train.py``, ``evaluate.py``, ``preview.py``, ``data_prep/``) call
it; the library (training, evaluation, model, solver, data, sim, maps, geometry) never imports
it (``tests/test_layering.py``). See ``docs/architecture.md``."""
