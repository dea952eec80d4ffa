"""``hybridoc export``: a disc scene in another simulator's format (the library functions are
in :mod:`hybridoc.workflows.mujoco`)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    emit_json,
    fmt,
    load_problem_arg,
    positive_float,
    positive_int,
    problem_arg,
    say,
    warn,
)
from hybridoc.errors import HybridocError
from hybridoc.outputs import check_folder, check_targets, write_text

__all__ = ["FORMATS", "register"]

#: The formats ``hybridoc export`` writes.
FORMATS = ("mjcf",)

# fewer MuJoCo steps per contact than this: a warning (sqrt(k) h > pi / 15, about 0.2)
_FEW_STEPS = 15


def _target(out: Path | None, name: str) -> Path | None:
    """The file to write: ``out`` itself, or ``out/<name>.xml`` when ``out`` is a folder;
    checked before the work (:mod:`hybridoc.outputs`: a writable folder, and no link or
    file hybridoc did not write at the name)."""
    if out is None:
        return None
    if out.is_dir():
        safe = "".join(c if c.isalnum() or c in "._-" else "-" for c in name).strip("-")
        path = check_folder(out) / f"{safe or 'scene'}.xml"
    else:
        check_folder(out.parent if str(out.parent) else Path("."))
        path = out
    check_targets(path)
    return path


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


def _compiles(text: str) -> str:
    """Whether MuJoCo compiles the text: a line for the report (MuJoCo is optional)."""
    try:
        import mujoco
    except ImportError:
        return "not checked: MuJoCo is not installed (pip install hybridoc[mujoco])"
    try:
        model = mujoco.MjModel.from_xml_string(text)
    except ValueError as exc:  # the exporter's bug, not the user's: exit 3 from main
        raise RuntimeError(f"MuJoCo cannot compile the exported model: {exc}") from None
    return f"MuJoCo {mujoco.__version__} compiles it ({model.nq} joints, {model.nu} motors)"


def cmd_export(args: argparse.Namespace) -> int:
    """Write a disc scene in another simulator's format.

    mjcf: a MuJoCo model. Each disc is a sphere on two slide joints (x and y) with its mass
    and radius, each wall a plane, and each control component a motor named by the
    problem's control labels, in their order. Gravity is off, contacts are frictionless
    (condim 1) with a spring-damper of stiffness --stiffness whose damping gives the scene's
    restitution (solref = -k -b), and the time step is T / (N K) for K = --substeps MuJoCo
    steps per control interval. The initial state is the keyframe "initial". The cost is not
    part of MJCF: hybridoc.workflows.mujoco computes it, and MuJoCo's gradient, from a
    model. Without --out the model goes to standard output.
    """
    from hybridoc.workflows.mujoco import (
        DEFAULT_STIFFNESS,
        DEFAULT_SUBSTEPS,
        contact_damping,
        scene_to_mjcf,
    )

    # the defaults live in the library; the parser (which must not import it) says them
    substeps = DEFAULT_SUBSTEPS if args.substeps is None else args.substeps
    stiffness = DEFAULT_STIFFNESS if args.stiffness is None else args.stiffness
    if args.json and args.out is None:
        raise HybridocError("--json needs --out FILE (the model itself goes to standard output)")
    ocp = load_problem_arg(args.problem)
    # a problem that is not a disc scene is refused here (one line), before any file
    text = scene_to_mjcf(ocp, substeps=substeps, stiffness=stiffness)
    geometry = ocp.capabilities.geometry  # bodies, walls, restitution: the scene's
    path = _target(args.out, ocp.name)
    if path is None:
        sys.stdout.write(text)
        sys.stdout.flush()
        return 0
    checked = _compiles(text)
    write_text(path, text)  # atomically; never through a link or over a user's file
    h = ocp.dt / substeps
    damping = contact_damping(geometry.restitution, stiffness)
    report = {
        "problem": ocp.name,
        "format": args.format,
        "path": str(path),
        "timestep": h,
        "substeps": substeps,
        "stiffness": stiffness,
        "damping": damping,
        "restitution": geometry.restitution,
        "steps_per_contact": math.pi / (math.sqrt(stiffness) * h),
        "control_labels": list(ocp.control_labels),
        "check": checked,
    }
    if report["steps_per_contact"] < _FEW_STEPS:
        warn(
            f"a contact spans only {report['steps_per_contact']:.3g} MuJoCo steps: its "
            f"restitution may be off by several percent; --substeps "
            f"{math.ceil(substeps * _FEW_STEPS / report['steps_per_contact'])} gives "
            f"{_FEW_STEPS} (docs: MuJoCo, restitution)"
        )
    if args.json:
        emit_json(report)
        return 0
    say(args, f"wrote {path}: MuJoCo model of {ocp.name}")
    rows = [
        ("bodies", f"{_count(geometry.n_bodies, 'disc')}, {_count(len(geometry.planes), 'wall')}"),
        ("motors", ", ".join(ocp.control_labels)),
        (
            "timestep",
            f"{fmt(h, 6)} s = T / (N K), N = {ocp.steps}, K = {substeps} substeps",
        ),
        (
            "contact",
            f"stiffness {fmt(stiffness, 6)}, damping {fmt(damping, 6)} for restitution "
            f"{fmt(geometry.restitution)}; about {report['steps_per_contact']:.3g} steps per "
            "contact",
        ),
        ("check", checked),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        say(args, f"  {k.ljust(width)}  {v}")
    return 0


def register(sub: Any) -> None:
    """Add ``export``."""
    p = sub.add_parser(
        "export",
        help="write a disc scene as a model of another simulator (MuJoCo's MJCF)",
        description=cmd_export.__doc__,
    )
    p.add_argument("format", choices=FORMATS, help="mjcf: a MuJoCo XML model")
    problem_arg(p)
    p.add_argument(
        "--substeps", metavar="K", type=positive_int, default=None,
        help="MuJoCo steps per control interval (default 10)",
    )  # fmt: skip
    p.add_argument(
        "--stiffness", metavar="k", type=positive_float, default=None,
        help="contact stiffness in 1/s^2 (default 1e+06): a contact lasts "
        "pi/sqrt(k) and needs sqrt(k) T/(N K) <= 1",
    )  # fmt: skip
    p.add_argument(
        "--out", metavar="FILE", type=Path, default=None,
        help="write the model to FILE (FILE/<problem>.xml if FILE is a folder); default: "
        "standard output",
    )  # fmt: skip
    p.add_argument(
        "--json", action="store_true",
        help="with --out: print one JSON object describing the file on stdout",
    )  # fmt: skip
    p.set_defaults(func=cmd_export)
