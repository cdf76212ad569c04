"""The layout a user gets in the Rerun viewer: the default blueprint read back from a recording,
and the loops' drawn coordinates (both axes must fill the square 2D view)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mrrig.offline.layout_check import read_blueprint, read_strips
from mrrig.rigio.recording import (
    ERROR_ENTITY,
    GAP_ENTITY,
    LOOP_FV_ENTITY,
    LOOP_FX_ENTITY,
    REPORT_ENTITY,
    nice_scale,
)
from tests.test_recording import run_events, synthetic_run, write_recording


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("layout") / "rig1.rrd"
    s = synthetic_run(3000)  # xd about +-0.13 m/s against f about +-800 N: 1:6000
    write_recording(path, s, run_events(s), {"frames_received": 3000, "faults": {}})
    return path


def test_blueprint_has_one_tab_per_task(recorded):
    root = read_blueprint(recorded)
    assert root.kind == "tabs"
    tabs = {tab.name: tab for tab in root.children}
    assert list(tabs) == [
        "Tracking",
        "Current",
        "Motion",
        "Adaptation",
        "Timing",
        "Hybrid simulation",
        "Events and summary",
    ]
    origins = {name: {v.origin: v for v in tab.views()} for name, tab in tabs.items()}
    assert set(origins["Tracking"]) == {"forces", ERROR_ENTITY, LOOP_FV_ENTITY, LOOP_FX_ENTITY}
    assert set(origins["Current"]) == {"current", "state"}
    assert set(origins["Motion"]) == {"displacement", "velocity", "acceleration"}
    assert set(origins["Adaptation"]) == {"adaptation", "temperature"}
    assert set(origins["Timing"]) == {"latency", GAP_ENTITY, "state"}
    events = origins["Events and summary"]
    assert events["events"].kind == "TextLog"
    assert events[REPORT_ENTITY].kind == "TextDocument"
    for loop in (LOOP_FV_ENTITY, LOOP_FX_ENTITY):
        view = origins["Tracking"][loop]
        assert view.kind == "2D"
        bounds = view.properties["VisualBounds2D"]["VisualBounds2D:range"][0]
        assert bounds["x_range"] == bounds["y_range"] == [-1.25, 1.25]


def test_every_time_series_names_its_unit_and_no_legend_covers_it(recorded):
    units = ("(N)", "(A)", "(m)", "(m/s)", "(m/s^2)", "(us)", "(ms)", "(degC)", "IDLE")
    for view in read_blueprint(recorded).views():
        if view.kind != "TimeSeries":
            continue
        assert any(u in view.name for u in units), view.name
        # no legend drawn over the plot: the title names the colours of several series
        assert view.properties["PlotLegend"]["PlotLegend:visible"] == [False]
    forces = next(v for v in read_blueprint(recorded).views() if v.origin == "forces")
    assert all(c in forces.name for c in ("desired red", "measured blue", "model green"))


@pytest.mark.parametrize("entity", [LOOP_FV_ENTITY, LOOP_FX_ENTITY])
def test_loops_span_comparable_ranges_on_both_axes(recorded, entity):
    strips = read_strips(recorded, entity)
    assert len(strips) >= 10  # one per flush window
    points = np.concatenate(strips)
    span_x, span_y = np.ptp(points[np.isfinite(points).all(axis=1)], axis=0)
    assert 0.25 < span_x / span_y < 4.0, (span_x, span_y)
    assert span_x <= 2.0 and span_y <= 2.0  # within the +-1 of the labelled full scale
    axes = read_strips(recorded, f"{entity}/axes")
    assert axes and np.ptp(np.concatenate(axes), axis=0).tolist() == [2.0, 2.0]


def test_summary_text_is_in_the_recording(recorded):
    from mrrig.offline.rrd_scan import open_rrd

    texts = [
        row["TextDocument:text"][0]
        for chunk in open_rrd(recorded).stream()
        if chunk.entity_path == f"/{REPORT_ENTITY}"
        for row in chunk.to_record_batch().to_pylist()
    ]
    assert texts and texts[0].startswith("# Run summary: rig rig1")


@pytest.mark.parametrize(
    ("value", "scale"),
    [(0.13, 0.2), (0.2, 0.2), (0.21, 0.5), (801.0, 1000.0), (7.0, 10.0), (0.0, 1.0)],
)
def test_nice_scale(value, scale):
    assert nice_scale(value) == pytest.approx(scale)
