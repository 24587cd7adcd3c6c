"""Plan figures: a synthetic plan built from the kinematics is drawn to PNG files."""

from __future__ import annotations

import copy
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hrm_ctrl import kinematics
from hrm_ctrl.errors import PlanFileError
from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.formats.plots import (
    ANGLES_PNG,
    ARM_PNG,
    BACKBONE_PNG,
    PlotError,
    write_plan_figures,
)
from hrm_ctrl.model import default_robot

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
N_STEPS = 25


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from the IHDR chunk of a PNG file (checks the signature)."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


def synthetic_plan(seed: int = 3, backbone_every: int | None = 12) -> dict[str, Any]:
    """A plan whose steps blend three random configurations within the limits;
    the path is the end point's trajectory, the backbone a dense polyline through
    the joint centres."""
    model = default_robot()
    rng = np.random.default_rng(seed)
    keys = rng.uniform(-0.8, 0.8, size=(3, 2, 12)) * model.limit_alpha
    s = np.linspace(0.0, 2.0, N_STEPS)
    idx = np.minimum(s.astype(int), 1)
    w = (s - idx)[:, None, None]
    angles = keys[idx] * (1.0 - w) + keys[idx + 1] * w  # (S, 2, 12)
    alpha, theta = angles[:, 0], angles[:, 1]
    joints = kinematics.joint_centres(model, alpha, theta)  # (S, 13, 3)
    tips = joints[:, -1]
    travel = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(tips, axis=0), axis=1))))
    steps = []
    for k in range(N_STEPS):
        step = {
            "travel_mm": float(travel[k]),
            "alpha_rad": alpha[k].tolist(),
            "theta_rad": theta[k].tolist(),
            "joints_mm": joints[k].tolist(),
        }
        if backbone_every and k % backbone_every == 0:
            t = np.linspace(0.0, 12.0, 200)
            i = np.minimum(t.astype(int), 11)
            f = (t - i)[:, None]
            step["backbone_mm"] = (joints[k][i] * (1 - f) + joints[k][i + 1] * f).tolist()
        steps.append(step)
    return {
        "format": "hrm-plan/1",
        "robot": model.to_dict(),
        "path_mm": tips.tolist(),
        "steps": steps,
        "report": {"max_tip_error_mm": 0.0},
        "scenario": {"name": "synthetic", "obstacles": []},
    }


@pytest.fixture(scope="module")
def plan() -> dict[str, Any]:
    return synthetic_plan()


def test_writes_three_valid_pngs(plan: dict[str, Any], tmp_path: Path) -> None:
    out = tmp_path / "figs" / "nested"  # created on demand
    paths = write_plan_figures(plan, out)
    assert [p.name for p in paths] == [BACKBONE_PNG, ARM_PNG, ANGLES_PNG]
    for p in paths:
        assert p.parent == out and p.stat().st_size > 10_000
        width, height = png_size(p)
        assert width > 500 and height > 500
    assert png_size(out / ARM_PNG) == (1100, 770)  # 10 x 7 in at 110 dpi
    assert png_size(out / ANGLES_PNG) == (1100, 825)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in paths)  # no temps


def test_default_steps_are_those_with_backbones(plan: dict[str, Any]) -> None:
    data = PlanDoc.from_dict(plan)
    assert sorted(data.backbones_mm) == [0, 12, 24]
    assert data.joints_mm.shape == (N_STEPS, 13, 3)
    assert data.joint_limits_deg[0] == pytest.approx(60.0)


def test_a_plan_doc_draws_as_its_dict_does(plan: dict[str, Any], tmp_path: Path) -> None:
    a = write_plan_figures(plan, tmp_path / "a", steps=[0, 12])
    b = write_plan_figures(PlanDoc.from_dict(plan), tmp_path / "b", steps=[0, 12])
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]


def test_without_backbones_no_backbone_figure(tmp_path: Path) -> None:
    paths = write_plan_figures(synthetic_plan(backbone_every=None), tmp_path, steps=[0, 5])
    assert [p.name for p in paths] == [ARM_PNG, ANGLES_PNG]


def test_figures_differ_with_the_steps_drawn(plan: dict[str, Any], tmp_path: Path) -> None:
    a = write_plan_figures(plan, tmp_path / "a", steps=[0])
    b = write_plan_figures(plan, tmp_path / "b", steps=[0, 12, 24])
    assert [p.name for p in a] == [p.name for p in b] == [BACKBONE_PNG, ARM_PNG, ANGLES_PNG]
    assert (tmp_path / "a" / ARM_PNG).read_bytes() != (tmp_path / "b" / ARM_PNG).read_bytes()


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda p: p.pop("steps"), "missing key 'steps'"),
        (lambda p: p.pop("path_mm"), "missing key 'path_mm'"),
        (lambda p: p.pop("format"), "missing key 'format'"),
        (lambda p: p["robot"].pop("links_mm"), "robot: missing key 'links_mm'"),
        (lambda p: p["steps"][3].pop("alpha_rad"), "steps[3]: missing key 'alpha_rad'"),
        (lambda p: p["steps"][7].pop("joints_mm"), "steps[7]: missing key 'joints_mm'"),
        (lambda p: p["steps"][2].pop("travel_mm"), "steps[2]: missing key 'travel_mm'"),
        (lambda p: p.update(format="hrm-plan/0"), "expected 'hrm-plan/1'"),
        (lambda p: p["steps"][1]["theta_rad"].pop(), "steps[1].theta_rad: expected an array"),
        (lambda p: p["steps"][4]["alpha_rad"].__setitem__(0, "x"), "steps[4].alpha_rad"),
        (
            lambda p: p["path_mm"][0].__setitem__(1, float("nan")),
            "path_mm[0][1]: expected a finite number, got nan",
        ),
        (lambda p: p.update(steps=[]), "steps: expected a non-empty list"),
        (lambda p: p["steps"][5].update(travel_mm=[1, 2]), "steps[5].travel_mm: expected a number"),
        (lambda p: p["steps"][6].update(backbone_mm=[[1, 2]]), "steps[6].backbone_mm"),
    ],
)
def test_bad_plan_raises_naming_the_key(
    plan: dict[str, Any], tmp_path: Path, mutate, needle: str
) -> None:
    bad = copy.deepcopy(plan)
    mutate(bad)
    out = tmp_path / "figs"
    with pytest.raises(PlanFileError) as info:
        write_plan_figures(bad, out)
    assert needle in str(info.value)
    assert "\n" not in str(info.value)
    assert not out.exists()  # nothing written


def test_bad_step_choice_and_unwritable_dir(plan: dict[str, Any], tmp_path: Path) -> None:
    with pytest.raises(PlotError, match="out of range"):
        write_plan_figures(plan, tmp_path / "x", steps=[N_STEPS])
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(PlotError, match="cannot create figure directory"):
        write_plan_figures(plan, blocker / "figs", steps=[0])
