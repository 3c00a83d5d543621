"""Run identity across versions: a network option added after a run was stored, at its
default, is the same network (the old checkpoint stays usable); at another value it differs."""

from __future__ import annotations

from seglocnet_jax.app import runs


def _stored(**model):
    return {"model": {"name": "tiny", "embed_dim": 64, **model}, "map": {"channels": ["road"]}}


def test_a_model_key_added_later_at_its_default_is_no_difference():
    stored = _stored()  # written before geometric_attention / camera_queries existed
    current = _stored(geometric_attention=False, camera_queries=16, token_stride=16)
    assert runs.config_diff(stored, current, only="model") == []


def test_a_model_key_added_later_at_another_value_is_named():
    stored = _stored()
    current = _stored(geometric_attention=True, camera_queries=16)
    assert runs.config_diff(stored, current, only="model") == [
        "model.geometric_attention: '<absent>' -> True"
    ]


def test_a_key_removed_or_unknown_is_still_a_difference():
    assert runs.config_diff(_stored(old_option=3), _stored(), only="model") == [
        "model.old_option: 3 -> '<absent>'"
    ]
    assert runs.config_diff(_stored(), _stored(not_a_field=False), only="model") == [
        "model.not_a_field: '<absent>' -> False"
    ]
