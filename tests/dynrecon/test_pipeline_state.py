"""`dynrecon.pipeline_state`: the inputs key that decides whether a stage of `dynrecon run` reruns."""

from __future__ import annotations

from dynrecon.pipeline_state import inputs_key


def test_inputs_key_follows_contents_and_settings(tmp_path):
    a = tmp_path / "a.csv"
    a.write_text("1\n")
    key = inputs_key({"a": a}, {"x": 1})
    assert inputs_key({"a": a}, {"x": 1}) == key
    assert inputs_key({"a": a}, {"x": 2}) != key
    a.write_text("2\n")
    assert inputs_key({"a": a}, {"x": 1}) != key
