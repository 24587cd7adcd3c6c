"""The drivers' contract with the rope layer (drivers.rope_model): the rope layer's
``Actuation`` implements every Protocol, a motor subset the ``RopeModel`` (without the
whole arm), the limits-only test doubles ``MotorLimits``; every method accepts the
Protocol's parameters; the drivers ask the model for the joint count and never probe it."""

from __future__ import annotations

import ast
import inspect
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import drivers
from drivers.rope_model import ArmRopeModel, JointPath, MotorLimits, RopeModel
from drivers.safety.limits import SetpointError
from drivers.safety.subset import ActuationSubset
from drivers.sources import JogSource
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from tests.drivers.safety import test_limits, test_supervisor, test_supervisor_stop_ramp

ACT = load_actuation(default_robot())
SUB = ActuationSubset(ACT, ("j01r0", "j07r2", "j12r1"))
PROTOCOLS = (MotorLimits, RopeModel, ArmRopeModel)
DOUBLES = [
    test_supervisor.Limits(),
    test_supervisor_stop_ramp.AccelLimits(),
    test_limits.Limits(),
    test_limits.AccelLimits(),
    test_limits.NoRate(),
]


def members(protocol: type) -> dict[str, Any]:
    """The Protocol's own and inherited members (name -> the attribute on the class)."""
    out: dict[str, Any] = {}
    for base in reversed(protocol.__mro__):
        if base in PROTOCOLS:
            out.update({k: v for k, v in vars(base).items() if not k.startswith("_")})
    return out


def assert_accepts(impl: Any, proto: Any, where: str) -> None:
    """``impl`` takes every call ``proto`` allows: each parameter under the same name and
    kind, optional where the Protocol's is; its own extra parameters optional."""
    want = inspect.signature(proto).parameters
    have = inspect.signature(impl).parameters
    for name, p in want.items():
        if name == "self":
            continue
        assert name in have, f"{where}: no parameter {name!r}"
        q = have[name]
        assert q.kind == p.kind, f"{where}: {name!r} is {q.kind}, the Protocol's {p.kind}"
        if p.default is not inspect.Parameter.empty:
            assert q.default is not inspect.Parameter.empty, f"{where}: {name!r} not optional"
    extra = [q for n, q in have.items() if n not in want and n != "self"]
    for q in extra:
        assert q.default is not inspect.Parameter.empty or q.kind in (
            q.VAR_POSITIONAL,
            q.VAR_KEYWORD,
        ), f"{where}: its own parameter {q.name!r} is required"


@pytest.mark.parametrize(
    ("model", "protocols"),
    [
        (ACT, PROTOCOLS),
        (SUB, (MotorLimits, RopeModel)),
        *((d, (MotorLimits,)) for d in DOUBLES),
    ],
    ids=["actuation", "subset", *(type(d).__qualname__ for d in DOUBLES)],
)
def test_each_model_implements_its_protocols_fully(model: Any, protocols: tuple) -> None:
    for proto in PROTOCOLS:
        assert isinstance(model, proto) == (proto in protocols), proto.__name__
    for proto in protocols:
        for name, member in members(proto).items():
            where = f"{type(model).__name__}.{name} ({proto.__name__})"
            if callable(member) and not isinstance(member, property):
                assert_accepts(getattr(model, name), member, where)
            else:
                assert not callable(getattr(model, name)), where


def test_the_arrays_and_the_joint_count_are_the_models() -> None:
    for model in (ACT, SUB):
        n = len(model.motor_ids)
        for name in ("counts_min", "counts_max", "max_rate_counts_per_s",
                     "max_accel_counts_per_s2", "max_jerk_counts_per_s3"):  # fmt: skip
            assert np.asarray(getattr(model, name)).shape == (n,), name
        assert model.n_joints == ACT.robot.n_joints == 12
        assert model.motor_label(0).startswith(f"{model.motor_ids[0]} (joint ")
    assert ACT.whole_arm is ACT and SUB.whole_arm is None
    assert SUB.max_accel_counts_per_s2.tolist() == [
        ACT.max_accel_counts_per_s2[ACT.motor_ids.index(m)] for m in SUB.motor_ids
    ]
    line = ACT.joint_line(np.zeros(ACT.n_motors, np.int64), np.zeros(ACT.n_motors, np.int64))
    assert isinstance(line, JointPath)
    assert ACT.command_tension_N == ACT.routing.command_tension_N
    assert (ACT.limit_alpha, ACT.limit_theta) == (ACT.robot.limit_alpha, ACT.robot.limit_theta)


def test_a_subset_maps_counts_with_the_other_motors_held() -> None:
    """The subset's angles are the rope layer's of its counts with every other motor at
    its fill value (0 counts, within the limits)."""
    c = np.array([[0, 0, 0], [3000, -2000, 1000]], dtype=np.int64)
    alpha, theta, res = SUB.angles_from_counts(c)
    full = np.zeros((2, ACT.n_motors), dtype=np.int64)
    full[:, SUB.columns] = c
    a2, t2, r2 = ACT.angles_from_counts(full)
    assert np.array_equal(alpha, a2) and np.array_equal(theta, t2)
    assert np.array_equal(res, r2[:, SUB.columns])
    z = np.zeros(12)
    assert np.array_equal(SUB.counts_from_angles(z, z), ACT.counts_from_angles(z, z)[SUB.columns])


class TwoJoints:
    """A rope model of an arm of two joints (one motor per angle, 1000 counts a rad),
    limits only and joint limits of 0.5 rad: the joint count is the model's."""

    motor_ids = ("a0", "t0", "a1", "t1")
    counts_min = np.full(4, -(10**6), dtype=np.int64)
    counts_max = np.full(4, 10**6, dtype=np.int64)
    max_rate_counts_per_s = np.full(4, 1e5)
    max_accel_counts_per_s2 = np.full(4, 1e6)
    max_jerk_counts_per_s3 = np.full(4, 1e8)
    n_joints = 2
    whole_arm = None

    def __init__(self) -> None:
        self.angle_shapes: list[tuple[int, ...]] = []

    def motor_label(self, i: int) -> str:
        return self.motor_ids[i]

    def check_counts(self, counts: Any, previous: Any = None, dt_s: Any = None) -> None:
        pass

    def counts_from_angles(self, alpha: Any, theta: Any, tension_N: Any = None) -> np.ndarray:
        a, t = np.asarray(alpha), np.asarray(theta)
        self.angle_shapes.append(a.shape)
        return np.rint(1000 * np.stack([a, t], axis=-1).reshape(*a.shape[:-1], 4)).astype(np.int64)

    def angles_from_counts(self, counts: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.asarray(counts, dtype=np.float64).reshape(*np.shape(counts)[:-1], 2, 2) / 1000
        return q[..., 0], q[..., 1], np.zeros(np.shape(counts))

    def check_angles(self, alpha: Any, theta: Any) -> None:
        if np.abs(alpha).max() >= 0.5 or np.abs(theta).max() >= 0.5:
            raise SetpointError("outside +-0.5 rad")


def test_a_jog_takes_the_joint_count_from_the_model() -> None:
    model = TwoJoints()
    assert isinstance(model, RopeModel) and not isinstance(model, ArmRopeModel)
    JogSource(model, "a1", 1000.0, 0.2).precheck(0.01)  # 200 counts: 0.2 rad
    assert model.angle_shapes == [(2,)]  # the straight arm of two joints
    with pytest.raises(SetpointError, match=r"leaves the joint limits \(outside \+-0.5 rad\)"):
        JogSource(model, "a1", 1000.0, 0.6).precheck(0.01)


DRIVERS = Path(drivers.__file__).parent
ROPE_MODULES = [
    "rope_model.py",
    "safety/limits.py",
    "safety/subset.py",
    "safety/watches.py",
    *(f"sources/{p.name}" for p in sorted((DRIVERS / "sources").glob("*.py"))),
]


@pytest.mark.parametrize("path", ROPE_MODULES)
def test_no_module_probes_what_it_is_given(path: str) -> None:
    """The rope model (and what else these modules are handed) is used through its
    Protocol: no getattr / hasattr, no joint count of their own."""
    tree = ast.parse((DRIVERS / path).read_text())
    probes = [
        f"line {node.lineno}: {node.func.id}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in ("getattr", "hasattr")
    ]
    assert not probes, probes
    twelve = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value == 12]
    assert not twelve, f"a joint count of 12 on lines {twelve}"


STATIC_CHECK = """
from drivers.rope_model import ArmRopeModel, MotorLimits, RopeModel
from drivers.safety.subset import ActuationSubset
from drivers.sources import CountsSource, HoldSource, PausableSource, SetpointSource
from drivers.sources import TabledSource
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation

act = load_actuation(default_robot())
whole: ArmRopeModel = act
subset: RopeModel = ActuationSubset(act, ("j01r0",))
limits: MotorLimits = subset
table: TabledSource = CountsSource(act, act.counts_min[None, :], 0.01)
played: SetpointSource = PausableSource(table, act)
held: SetpointSource = HoldSource(3)
"""


def test_the_protocols_hold_statically(tmp_path: Path) -> None:
    """mypy: the actuation is an ``ArmRopeModel``, a subset a ``RopeModel``, the sources
    setpoint sources, and the drivers' rope-model modules use nothing of what they are
    given beyond its Protocol (an attribute outside it is an error here)."""
    snippet = tmp_path / "contract.py"
    snippet.write_text(STATIC_CHECK)
    cmd = [
        sys.executable, "-m", "mypy", "--no-incremental", "--follow-imports=silent",
        "--ignore-missing-imports", "--cache-dir", str(tmp_path / "cache"), str(snippet),
        *(str(DRIVERS / p) for p in ROPE_MODULES),
    ]  # fmt: skip
    root = DRIVERS.parent
    res = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300, check=False)
    assert res.returncode == 0, res.stdout + res.stderr
