"""docs/vehicle.md stays true: its generated tables equal what the graphs give."""

import pytest

from vehicle_graphs import EXPERIMENTS, MODELS
from vehicle_graphs.doc import doc_block, doc_path, models_table, param_table


@pytest.fixture(scope="module")
def text():
    return doc_path().read_text()


def test_parameter_table_is_current(text):
    assert doc_block(text, "PARAMS") == param_table(), \
        "run `python -m vehicle_graphs.doc update params`"


def test_models_table_is_current(text):
    assert doc_block(text, "MODELS") == models_table(), \
        "run `python -m vehicle_graphs.doc update models`"


def test_every_model_and_experiment_is_documented(text):
    for name in list(MODELS) + list(EXPERIMENTS):
        assert f"`{name}`" in text, name
    assert "bondgraph simulate vehicle_full --experiment vehicle_full_throttle_high" in text
    assert "bondgraph plot full_throttle.csv" in text


def test_update_rewrites_only_the_block(tmp_path, text):
    from vehicle_graphs.doc import update_docs

    p = tmp_path / "vehicle.md"
    stale = text.replace(doc_block(text, "PARAMS"), "| stale |", 1)
    p.write_text(stale)
    assert update_docs(["PARAMS"], path=p) == ["PARAMS"]
    assert p.read_text() == text
