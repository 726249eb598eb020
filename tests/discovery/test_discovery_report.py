"""The discovery report's figures: the score plot keeps its whole x-label on the canvas
and marks the winner and the runner-up; the residual and temperature plots show the operating
point (speed, current) beneath, and the residual-against-variable plot where the run was.

One simulated case with a hidden effect (the one ``test_discovery_workflow`` names) gives a
discovery with a winner; the figures are built unsaved and inspected.
"""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from benchmarks import discovery as bench
from thermal_edge.discovery import report, workflow
from thermal_edge.lptn import Role

SHORT = 7200.0  # s, as in test_discovery_workflow


@pytest.fixture(scope="module")
def figs():
    raw, run, expected, _ = bench.simulated_run("speed_convection:R_e_hous", "heldout_drive", seed=3, duration_s=SHORT)
    disc = workflow.discover(raw, run, bench.hidden.builder(bench.PM10KW))
    assert disc.named is not None and disc.named.fit.label == expected
    out = report.build_figures(disc)
    yield disc, out
    import matplotlib.pyplot as plt

    plt.close("all")


def _inside(fig, artist) -> bool:
    fig.canvas.draw()
    box = artist.get_window_extent(fig.canvas.get_renderer())
    w, h = fig.canvas.get_width_height()
    return box.x0 >= 0 and box.y0 >= 0 and box.x1 <= w and box.y1 <= h


def test_score_plot_has_its_whole_x_label_and_marks_winner_and_runner_up(figs):
    disc, out = figs
    name, fig = out["scores"]
    assert name == "scores.png"
    ax = fig.axes[0]
    assert "score test" in ax.get_xlabel() and _inside(fig, ax.xaxis.label)
    labels = [t.get_text() for t in ax.get_yticklabels()]
    win, ru = disc.rounds[0].winner.fit.label, disc.rounds[0].runner_up.fit.label
    assert win in labels and ru in labels
    colour = {lab: bar.get_facecolor() for lab, bar in zip(labels, ax.patches)}
    import matplotlib.colors as mc

    assert np.allclose(colour[win], mc.to_rgba("tab:green")) and np.allclose(colour[ru], mc.to_rgba("tab:orange"))
    notes = [t.get_text().strip() for t in ax.texts]
    assert "winner" in notes and "runner-up" in notes
    assert all(_inside(fig, t) for t in ax.texts)


@pytest.mark.parametrize("kind", ["time", "temperature"])
def test_time_plots_show_the_operating_point_beneath(figs, kind):
    disc, out = figs
    _, fig = out[kind]
    run = disc.data.run
    speed, current = (disc.final.model.input_name(r) for r in (Role.SPEED, Role.CURRENT))
    below = [ax for ax in fig.axes if ax.get_ylabel() == "speed (rpm)"]
    twin = [ax for ax in fig.axes if ax.get_ylabel() == "current (A)"]
    assert len(below) == 1 and len(twin) == 1
    # beneath every sensor panel, on the same time axis
    sensor_axes = [ax for ax in fig.axes if ax not in below + twin]
    assert len(sensor_axes) == len(disc.data.sensors)
    assert all(below[0].get_position().y1 <= ax.get_position().y0 for ax in sensor_axes)
    assert below[0].get_xlabel() == "time since start (h)"
    step = max(1, len(run) // 4000)
    np.testing.assert_allclose(below[0].lines[0].get_ydata(), np.abs(run.columns[speed][::step]))
    np.testing.assert_allclose(twin[0].lines[0].get_ydata(), run.columns[current][::step])


def test_residual_against_a_variable_shows_where_the_run_was(figs):
    disc, out = figs
    _, fig = out["var"]
    ns = len(disc.data.sensors)
    assert len(fig.axes) == 2 * ns
    for low in fig.axes[ns:]:
        assert low.get_ylabel().startswith("share of")
        # one step histogram for the training and one for the held-out part, heights shares of samples
        assert len(low.patches) == 2
        for patch in low.patches:
            heights = patch.get_path().vertices[:, 1]
            assert heights.max() <= 1.0 + 1e-9
