"""Plan figures with an environment: the 3D figures draw it, clearance.png plots the arm's."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.formats.plots import (
    ANGLES_PNG,
    ARM_PNG,
    BACKBONE_PNG,
    CLEARANCE_PNG,
    _draw_environment,
    _wall_outline,
    write_plan_figures,
)
from hrm_ctrl.planning.environment import Box, Environment, Pipe, RoundOpening, Wall
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.report import clearance_summary, plan_file_clearance
from tests.hrm_ctrl.formats.test_plots import png_size, synthetic_plan


def environment_of(doc: dict[str, Any]) -> Environment:
    tips = np.array(doc["path_mm"])
    mid = tips[len(tips) // 2]
    axis = KnownPath.from_points(tips[len(tips) // 2 :])
    wall = Wall(
        mid,
        np.array([1.0, 0.0, 0.0]),
        openings=(RoundOpening(mid, 80.0),),
        bounds=((mid, np.array([0.0, 0.0, 1.0])),),
    )
    box = Box(mid + np.array([0.0, 300.0, 0.0]), np.array([50.0, 60.0, 70.0]))
    return Environment((Pipe(axis, 70.0), wall, box))


@pytest.fixture(scope="module")
def plan_with_env() -> dict[str, Any]:
    doc = synthetic_plan()
    env = environment_of(doc)
    doc["scenario"] = {"name": "synthetic", "environment": env.to_dict()}
    c = clearance_summary(
        plan_file_clearance(PlanDoc.from_dict(doc, "synthetic"), np.full(12, 30.0))
    )
    doc["report"]["clearance_mm"] = c
    return doc


def test_a_plan_with_an_environment_gets_clearance_png(plan_with_env, tmp_path: Path) -> None:
    written = write_plan_figures(plan_with_env, tmp_path)
    assert [p.name for p in written] == [BACKBONE_PNG, ARM_PNG, ANGLES_PNG, CLEARANCE_PNG]
    w, h = png_size(tmp_path / CLEARANCE_PNG)
    assert w > 500 and h > 300


def test_the_environment_is_drawn_in_3d(plan_with_env) -> None:
    from matplotlib.figure import Figure

    doc = PlanDoc.from_dict(plan_with_env, "synthetic")
    ax = Figure().add_subplot(projection="3d")
    drawn = _draw_environment(ax, doc.environment, doc.path_mm.mean(axis=0))
    pipe, wall, box = doc.environment.obstacles
    # rings of the pipe's radius around its axis, the wall's opening, 12 box edges
    rings = [d for d in drawn if len(d) == 37]
    assert len(rings) >= pipe.axis.length / 15.0
    r = pipe.axis.distance_to(rings[0])
    np.testing.assert_allclose(r, pipe.inner_radius, atol=1e-6)
    opening = [d for d in drawn if len(d) == 49]
    assert len(opening) == 1
    np.testing.assert_allclose(
        np.linalg.norm(opening[0] - wall.openings[0].centre, axis=1), 40.0, atol=1e-9
    )
    edges = [d for d in drawn if len(d) == 2]
    assert len(edges) == 12
    np.testing.assert_allclose(
        np.abs(np.concatenate(edges) - box.centre), 0.5 * box.size * np.ones((24, 3))
    )
    assert len(ax.collections) >= 1  # the wall's patch
    assert _draw_environment(ax, None, np.zeros(3)) == []


def test_a_bounded_wall_is_drawn_only_where_it_exists() -> None:
    c = np.array([100.0, 0.0, 0.0])
    w = Wall(
        c,
        np.array([1.0, 0.0, 0.0]),
        openings=(RoundOpening(c, 80.0),),
        bounds=((c, np.array([0.0, 1.0, 0.0])),),
    )
    patch, outlines = _wall_outline(w, np.zeros(3))
    assert (patch[:, 1] >= -1e-9).all() and patch[:, 1].max() > 40.0
    np.testing.assert_allclose(patch[:, 0], 100.0)
    np.testing.assert_allclose(np.linalg.norm(outlines[0] - c, axis=1), 40.0)
