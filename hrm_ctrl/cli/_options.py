"""The options several commands share, each declared here once.

Each adder declares its options' names, types, defaults, metavars and help texts.  A
command's ``register()`` (and the console's parsers of its own commands) call these; what
differs between commands is said by parameters: what ``--json`` prints, what ``--out``
writes, and ``when`` an option applies (``with --sim``, ``with --live``: the start of its
help text).

Units in metavars: ``MM``, ``MM_S``, ``S``, ``HZ``, ``NEWTON``, ``COUNTS``; ``N`` counts
things.  An adder imports what its choices or default need (the log formats, the simulated
wires, the default tip speed) when it runs: ``hrm`` registers a command's arguments only
when that command is parsed (:func:`hrm_ctrl.cli.build_parser`), so ``hrm --help`` and
``hrm --version`` import none of it.

>>> p = argparse.ArgumentParser(prog="hrm x")
>>> add_json(p, "the summary")
>>> add_sim(p, wire=True, arm=SimArm.PERTURB_OR_TRUTH)
>>> a = p.parse_args(["--json", "--sim", "--perturb", "3"])
>>> a.json, a.sim, a.wire, a.perturb, a.truth
(True, True, 'virtual', 3, None)
>>> [x.help for x in p._actions if x.dest == "json"]
['print the summary as JSON']
"""

from __future__ import annotations

import argparse
from enum import Enum
from pathlib import Path
from typing import Any

RUNS_DIR = Path("runs")


def when_prefix(when: str | None, text: str) -> str:
    """``text`` as the help of an option that applies only ``when``.

    >>> when_prefix("with --sim", "the simulated arm"), when_prefix(None, "x")
    ('with --sim: the simulated arm', 'x')
    """
    return f"{when}: {text}" if when else text


# ----------------------------------------------------------------------------- output
def add_json(parser: argparse.ArgumentParser, what: str) -> None:
    """``--json``: print ``what`` (``the summary``, ``the report``) as JSON."""
    parser.add_argument("--json", action="store_true", help=f"print {what} as JSON")


def add_out(
    parser: argparse.ArgumentParser, *, metavar: str, what: str, default: Path | None = None
) -> None:
    """``--out METAVAR``: the file (or folder) a command writes, ``what`` its help."""
    parser.add_argument("--out", type=Path, default=default, metavar=metavar, help=what)


# ------------------------------------------------------------------------ robot, store
def add_robot(parser: argparse.ArgumentParser) -> None:
    """``--robot FILE``: the robot description replacing the one shipped with hrm."""
    parser.add_argument(
        "--robot", type=Path, default=None, metavar="FILE",
        help="robot description TOML (default: the one shipped with hrm)",
    )  # fmt: skip


def nonempty_path(text: str) -> Path:
    """A path option's value; an empty one is refused (``Path("")`` is the current folder,
    which an empty ``--calibrations ''``, say from an unset shell variable, never means).

    >>> nonempty_path("store")
    PosixPath('store')
    >>> nonempty_path("")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: empty path
    """
    if not text:
        raise argparse.ArgumentTypeError("empty path")
    return Path(text)


class Uncalibrated(Enum):
    """What ``--uncalibrated`` does in a command (its help text)."""

    MODEL = "the robot description's values, not the calibration store's"
    DRIVES = (
        "enable the drives without a calibration (explicit override: the robot "
        "description's values)"
    )


def add_calibration(
    parser: argparse.ArgumentParser,
    uncalibrated: Uncalibrated | None = None,
    *,
    when: str | None = None,
) -> None:
    """``--calibrations DIR`` (the calibration store) and, with ``uncalibrated``,
    ``--uncalibrated`` (``when``: the condition its help names)."""
    from hrm_ctrl.cli._common import CALIBRATIONS_ENV, DEFAULT_CALIBRATIONS

    parser.add_argument(
        "--calibrations", type=nonempty_path, default=None, metavar="DIR",
        help=f"calibration store (default: ${CALIBRATIONS_ENV}, else ~/{DEFAULT_CALIBRATIONS})",
    )  # fmt: skip
    if uncalibrated is not None:
        parser.add_argument(
            "--uncalibrated", action="store_true", help=when_prefix(when, uncalibrated.value)
        )


# -------------------------------------------------------------------------------- box
BUS_METAVAR = "NAME=INTERFACE:CHANNEL[@BITRATE]"


def bus_override(text: str) -> Any:
    """``--bus`` value: :func:`drivers.config.parse_bus_override`, its error as argparse's
    (one line naming the option, exit 2).

    >>> bus_override("can0=virtual:a@500000").bitrate
    500000
    >>> bus_override("can0")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: 'can0': expected NAME=INTERFACE:CHANNEL[@BITRATE]
    """
    from drivers.config import BusConfigError, parse_bus_override

    try:
        return parse_bus_override(text)
    except BusConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_bus(
    parser: argparse.ArgumentParser,
    *,
    overrides: bool = True,
    take_over: bool = False,
    config_use: str | None = None,
) -> None:
    """``--config BOX.toml`` (the bus configuration; ``config_use``: what the command takes
    from it, when not its buses), with ``overrides`` ``--bus`` (repeatable: one bus of the
    configuration opened elsewhere), with ``take_over`` ``--take-over``."""
    what = f"bus configuration: {config_use}" if config_use else "bus configuration"
    parser.add_argument(
        "--config", type=Path, default=None, metavar="BOX.toml",
        help=f"{what} (default: the one shipped with hrm; a bus without an interface takes "
        "python-can's configuration: ~/can.conf, CAN_INTERFACE, ...)",
    )  # fmt: skip
    if overrides:
        parser.add_argument(
            "--bus", action="append", type=bus_override, default=[], metavar=BUS_METAVAR,
            help="open bus NAME of the bus configuration on this python-can interface and "
            "channel (and bitrate) instead; repeatable, one per bus",
        )  # fmt: skip
    if take_over:
        add_take_over(parser)


def add_take_over(parser: argparse.ArgumentParser) -> None:
    """``--take-over``: bring the drives up although another master is heard."""
    parser.add_argument(
        "--take-over", action="store_true",
        help="reset the drives even when another master is heard on the buses",
    )  # fmt: skip


def add_log(
    parser: argparse.ArgumentParser,
    *,
    what: str = "where the CAN logs and the run record go",
    when: str | None = None,
    formats: bool = True,
) -> None:
    """``--log-dir DIR`` (default ./runs; ``what`` goes there) and, with ``formats``,
    ``--log-format FORMAT`` (any python-can writes here: :func:`drivers.canlog.log_formats`)."""
    parser.add_argument(
        "--log-dir", type=Path, default=RUNS_DIR, metavar="DIR",
        help=when_prefix(when, f"{what} (default ./{RUNS_DIR})"),
    )  # fmt: skip
    if formats:
        from drivers.canlog import log_formats

        parser.add_argument(
            "--log-format", choices=log_formats(), default="blf", type=_log_format,
            help=when_prefix(
                when, "format of the CAN logs, as python-can writes them (default blf; "
                "log: candump; not mf4: python-can's MF4 writer cannot keep up)",
            ),
        )  # fmt: skip


def _log_format(text: str) -> str:
    """``--log-format``'s value; a format a run's log refuses is named with the reason
    (:data:`drivers.canlog.REFUSED_LOG_FORMATS`), any other the choices check."""
    from drivers.canlog import REFUSED_LOG_FORMATS

    if text in REFUSED_LOG_FORMATS:
        raise argparse.ArgumentTypeError(f"{text} refused: {REFUSED_LOG_FORMATS[text]}")
    return text


# -------------------------------------------------------------------- simulated box
class SimArm(Enum):
    """Which options choose the simulated arm: none, ``--perturb SEED``, or ``--perturb
    SEED`` or ``--truth TRUTH.toml`` (one of them)."""

    NONE = "none"
    PERTURB = "perturb"
    PERTURB_OR_TRUTH = "perturb or truth"


SIM_HELP = (
    "the simulated box (without a stored calibration: the robot description's "
    "values, said on stderr)"
)


def add_sim(
    parser: argparse.ArgumentParser,
    *,
    wire: bool = False,
    arm: SimArm = SimArm.PERTURB,
    when: str | None = None,
    process: bool = False,
) -> None:
    """``--sim`` (``when``: the condition it goes with), and with it ``--wire`` (with
    ``wire``; ``process``: the box in its own process its default) and the simulated
    arm's options (:class:`SimArm`), each ``with --sim``."""
    parser.add_argument("--sim", action="store_true", help=when_prefix(when, SIM_HELP))
    if wire:
        add_wire(parser, when="with --sim", process=process)
    add_sim_arm(parser, arm, when="with --sim")


def add_wire(parser: argparse.ArgumentParser, *, when: str | None, process: bool = False) -> None:
    """``--wire virtual|hrm_sim``: the in-process simulated box's buses; with ``process``
    also ``hrm_ipc``, the default: the simulated box in its own process."""
    from hrm_ctrl.cli._simwire import PROCESS_WIRE, SIM_WIRES

    in_process = "python-can virtual buses, or hrm_sim (simulated wire at the bitrate)"
    if process:
        in_process = (
            "hrm_ipc: the simulated box in its own process (default); virtual or hrm_sim: in "
            "this process, on python-can virtual buses or the simulated wire at the bitrate"
        )
    parser.add_argument(
        "--wire", choices=(PROCESS_WIRE, *SIM_WIRES) if process else SIM_WIRES,
        default=PROCESS_WIRE if process else "virtual", help=when_prefix(when, in_process),
    )  # fmt: skip


def add_sim_arm(
    parser: argparse.ArgumentParser,
    arm: SimArm,
    *,
    when: str | None,
    seed: int | None = None,
) -> None:
    """The simulated arm's options (:class:`SimArm`); ``seed``: ``--perturb``'s default."""
    if arm is SimArm.NONE:
        return
    group = parser.add_mutually_exclusive_group() if arm is SimArm.PERTURB_OR_TRUTH else parser
    default = "" if seed is None else f" (default seed {seed})"
    group.add_argument(
        "--perturb", type=int, default=seed, metavar="SEED",
        help=when_prefix(
            when, "a simulated arm that differs from its description, drawn from SEED: links "
            "+-2 mm, joint offsets +-1 deg, EA +-20%%, motor zeros +-5000 counts" + default,
        ),
    )  # fmt: skip
    if arm is SimArm.PERTURB_OR_TRUTH:
        group.add_argument(
            "--truth", type=Path, default=None, metavar="TRUTH.toml",
            help=when_prefix(
                when, "the simulated arm's truth file (TOML, hrm-sim-truth/1; docs/sim.md)"
            ),
        )  # fmt: skip


def add_physics(
    parser: argparse.ArgumentParser, *, when: str | None = "with --sim", default: str | None = None
) -> None:
    """``--physics EFFECTS``: the simulated arm's physics, as :meth:`sim_bus.physics.Physics.of`
    reads it (``when``: the condition it goes with; None: ``hrm sim``'s own arm), ``default``
    (None: none)."""
    parser.add_argument(
        "--physics", default=default, metavar="EFFECTS",
        help=when_prefix(
            when, "the simulated arm's physics: all, none or effects joined by commas "
            "(gravity, capstan, creep, backlash, sensor; defaults in docs/sim.md); default "
            f"{default or 'none'}",
        ),
    )  # fmt: skip


def sim_physics(spec: str | None, sim: bool = True) -> Any:
    """The :class:`sim_bus.physics.Physics` of ``--physics`` (None: not given); a bad
    value, or one without ``--sim`` (``sim``), is one line
    (:class:`~hrm_ctrl.errors.SimError`).

    >>> sim_physics("gravity,capstan").describe(), sim_physics(None)
    ('gravity,capstan', None)
    >>> sim_physics("gravity", sim=False)
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.SimError: --physics goes with --sim
    """
    from hrm_ctrl.errors import SimError
    from sim_bus.physics import Physics

    if spec is None:
        return None
    if not sim:
        raise SimError("--physics goes with --sim")
    return Physics.of(spec)


# ------------------------------------------------------------------------ plans, runs
def add_step(parser: argparse.ArgumentParser) -> None:
    """``--step MM``: the planner's lambda."""
    parser.add_argument(
        "--step", type=float, default=5.0, metavar="MM",
        help="lambda: travel between plan steps (default 5 mm)",
    )  # fmt: skip


def add_speed(parser: argparse.ArgumentParser, *, when: str | None = None) -> None:
    """``--speed MM_S``: the tip-speed cap of a playback (one default for every command)."""
    from hrm_ctrl.ropes.setpoints import DEFAULT_TIP_SPEED_MM_PER_S

    parser.add_argument(
        "--speed", type=float, default=DEFAULT_TIP_SPEED_MM_PER_S, metavar="MM_S",
        help=when_prefix(
            when, f"tip-speed cap of the playback (default {DEFAULT_TIP_SPEED_MM_PER_S:g} mm/s)"
        ),
    )  # fmt: skip


def add_allow_collision(
    parser: argparse.ArgumentParser, doing: str = "play a plan", *, when: str | None = None
) -> None:
    """``--allow-collision``: do ``doing`` although the arm meets an obstacle."""
    parser.add_argument(
        "--allow-collision", action="store_true",
        help=when_prefix(
            when, f"{doing} even if a link meets an obstacle of its environment (negative "
            "clearance)",
        ),
    )  # fmt: skip


def add_run_controls(parser: argparse.ArgumentParser) -> None:
    """How a plan is played (``hrm run``, the console's ``run``): ``--speed``, the run's
    script (``--pause-at``, ``--resume-after``, ``--abort-at``) and ``--allow-collision``."""
    add_speed(parser)
    parser.add_argument(
        "--pause-at", default=None, metavar="FRACTION",
        help="pause the plan (on its path) once this share of it is played, e.g. 30%%",
    )  # fmt: skip
    parser.add_argument(
        "--resume-after", default=None, metavar="S",
        help="with --pause-at: resume this long after the arm came to rest, e.g. 1s",
    )  # fmt: skip
    parser.add_argument(
        "--abort-at", default=None, metavar="FRACTION",
        help="abort the plan (stop on its path, end the run) at this share of it",
    )  # fmt: skip
    add_allow_collision(parser)


# ---------------------------------------------------------- rope-tension routines
def add_zero_options(parser: argparse.ArgumentParser) -> None:
    """The zero routine's settings (``hrm calibrate zero``, the console's)."""
    parser.add_argument(
        "--target-N", type=float, default=None, metavar="NEWTON",
        help="target tension (default the routing's pretension)",
    )  # fmt: skip
    parser.add_argument(
        "--tol-N", type=float, default=None, metavar="NEWTON",
        help="tension tolerance (default 0.2 N)",
    )  # fmt: skip
    parser.add_argument(
        "--max-travel-counts", type=int, default=None, metavar="COUNTS",
        help="longest travel of a motor from where it starts (default 12000 counts)",
    )  # fmt: skip


def add_stiffness_options(parser: argparse.ArgumentParser) -> None:
    """The stiffness routine's settings (``hrm calibrate stiffness``, the console's)."""
    parser.add_argument(
        "--sweep-N", type=float, default=None, metavar="NEWTON",
        help="tension each sweep spans above the pretension (default 10 N)",
    )  # fmt: skip
    parser.add_argument(
        "--steps", type=int, default=None, metavar="N", help="readings per sweep (default 5)"
    )


# ----------------------------------------------------------------- console over a box
def add_console_box(parser: argparse.ArgumentParser) -> None:
    """The arguments of a console over one box (``hrm console``, ``hrm status``): ``--sim``
    (``--wire``) or ``--config`` (``--bus``), ``--robot``, the calibration store, where the
    runs go, ``--take-over``."""
    add_bus(parser)
    add_sim(parser, wire=True, arm=SimArm.NONE, process=True)
    add_physics(parser)
    add_robot(parser)
    add_calibration(parser, Uncalibrated.DRIVES)
    add_log(parser, what="where each session's CAN logs and run record go")
    add_take_over(parser)
