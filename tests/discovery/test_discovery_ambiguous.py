"""Confusable effects end to end: a hidden magnet eddy loss in 3 h of the varied cycle, where a
bearing loss explains the held-out residual nearly as well.

Discovery must name the hidden effect first, say that it cannot separate it from the runner-up
(held-out gaps within their uncertainty), show the evidence (each one's predicted residual
against speed, current, ambient and time) and name the steady operating point that would tell
them apart; ``discover --json`` carries ``runner_up``, ``ambiguous`` and ``gap_noise_floor``.
The logic itself is tested on hand-made predictions in ``test_discovery_judge.py``; this case
(3 h of 1 Hz data) is ``slow``.
"""
from __future__ import annotations

import math

import pytest

from thermal_edge.discovery import bench, judge, workflow


@pytest.mark.slow
def test_magnet_eddy_loss_and_bearing_loss_are_reported_as_a_pair(tmp_path):
    raw, run, expected = bench.simulated_run("magnet_eddy_loss", "varied_drive", seed=9)
    disc = workflow.discover(raw, run, bench.hidden.builder(bench.PM10KW))
    d = disc.as_dict()
    assert d["named_effect"] == expected == "magnet_eddy_loss", d["rounds"]
    assert d["ambiguous"] is True and d["runner_up"] == "bearing_loss", d["comparison"]
    c = d["comparison"]
    # the pair is close by the rule: the held-out gaps within Z_SEPARATE standard errors
    assert c["gap_runner_up_k"] - c["gap_winner_k"] < judge.Z_SEPARATE * c["se_diff_k"]
    assert c["gap_runner_up_k"] < disc.rounds[0].reference_gap * (1 - disc.options.min_improvement)
    # evidence against the four operating variables, both predictions per bin
    assert [e["variable"] for e in c["evidence"]] == list(judge.EVIDENCE_VARS)
    assert all(len(e["centers"]) == len(e["winner"]) == len(e["runner_up"]) > 2 for e in c["evidence"])
    sep = c["separating_condition"]
    assert sep is not None and sep["diff_k"] == pytest.approx(abs(sep["winner_c"] - sep["runner_up_c"]))
    assert "or bearing_loss (this run cannot separate them)" in d["verdict"]
    assert math.isclose(d["gap_noise_floor"], disc.noise_k)
    # the report says it, with the figure
    from thermal_edge.discovery import report

    text = (tmp_path / "report.md") if report.write(disc, tmp_path) else None
    body = text.read_text()
    assert "Not sure between two" in body and "Separating condition" in body
    assert (tmp_path / "winner_vs_runner_up.png").exists() and (tmp_path / "temperature_time.png").exists()
