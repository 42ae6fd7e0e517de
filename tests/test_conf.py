"""Yes/no settings: words as users type them after ``--set`` are read as they mean, others refused."""

from __future__ import annotations

import pytest

from cosy_cli.conf import as_bool
from cosy_cli.errors import CosyError
from cosy_cli.evaluation import evaluate_stage
from cosy_cli.multiview import match_stage, refine_stage
from cosy_cli.pipeline.run_stage import parse_settings


@pytest.mark.parametrize("value,expected", [
    (True, True), (False, False), (1, True), (0, False), ("true", True), ("False", False), ("FALSE", False),
    ("yes", True), ("No", False), ("on", True), ("off", False), (" 1 ", True), ("0", False)])
def test_as_bool_reads_words_and_numbers(value, expected):
    assert as_bool(value, "k", "stage") is expected


@pytest.mark.parametrize("value", ["maybe", "", 2, 0.5, None, "tru"])
def test_as_bool_refuses_anything_else_naming_the_setting(value):
    with pytest.raises(CosyError, match=r"match setting refit = .* is not a yes/no value"):
        as_bool(value, "refit", "match")


def test_stages_read_set_values_as_meant():
    """``cosy run --set match.refit=off`` (a string: not JSON) turns refit off; before, bool("off") was True."""
    sets = parse_settings(["match.refit=off", "match.weak_links=False", "refine.rematch=no", "evaluate.vsd=Off",
                           "match.known_cameras=true"])
    assert sets["match"]["refit"] == "off" and sets["match"]["weak_links"] == "False"  # kept as typed
    m = match_stage.resolve_conf("paper", **sets["match"])
    assert m["refit"] is False and m["weak_links"] is False and m["known_cameras"] is True
    assert refine_stage.resolve_conf(None, **sets["refine"])["rematch"] is False
    assert evaluate_stage.resolve_conf("bop19", **sets["evaluate"])["vsd"] is False
    assert refine_stage.resolve_conf({"keep_unmatched": "no"})["output"] == "scene"  # the legacy key too
    with pytest.raises(CosyError, match="refine setting guard_views = 'perhaps'"):
        refine_stage.resolve_conf(None, guard_views="perhaps")
