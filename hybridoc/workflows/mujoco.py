"""Disc scenes in MuJoCo: the MJCF export, and rollouts, costs and gradients in MuJoCo.

Users learn controllers in mainstream simulators; this module puts a scene into MuJoCo so
that what MuJoCo produces (a control, a cost, a gradient) can be judged by hybridoc
(:func:`hybridoc.evaluate`, :func:`hybridoc.gradient`).

:func:`scene_to_mjcf`
    The MJCF text of a scene: each disc a sphere on two slide joints (x and y), each wall
    a plane, one motor per control component in the problem's ``control_labels`` order,
    no gravity, frictionless contacts (``condim="1"``) whose spring-damper is set by a
    negative ``solref = (-k, -b)``, and the time step ``h = T / (N K)`` for ``K``
    substeps per control interval.
:func:`load_model`
    A :class:`MujocoModel`: the compiled model with the maps between MuJoCo's arrays and
    hybridoc's, to roll out an ``(N, nu)`` or ``(N K, nu)`` control
    (:meth:`MujocoModel.rollout`), its cost in MuJoCo with the problem's own running and
    terminal costs (:meth:`MujocoModel.cost`), and MuJoCo's gradient of that cost from
    per-step Jacobians of ``mujoco.mjd_transitionFD`` chained backwards
    (:meth:`MujocoModel.cost_and_gradient`).
:func:`contact_damping`
    The damping ``b`` that gives a linear spring-damper contact of stiffness ``k`` the
    scene's coefficient of restitution.

MuJoCo is an optional dependency (``pip install hybridoc[mujoco]``): it is imported inside
the functions that need it, and its absence is one :class:`~hybridoc.errors.HybridocError`.

The contact model
    MuJoCo's soft constraint with ``solref = (-k, -b)`` and a constant impedance
    ``d = dmax`` (``solimp = (dmax, dmax, ...)``) makes the normal gap ``r`` of a contact
    follow ``r'' = -b r' - k r`` while the contact pushes (``r < 0``), whatever the masses:
    a linear spring-damper whose force cannot pull. Such a contact lasts about
    ``pi / sqrt(k)`` and ends when the force reaches zero; its restitution depends on the
    damping ratio ``zeta = b / (2 sqrt(k))`` alone (:func:`restitution_of_damping`),
    equal to 1 without damping. The export picks ``b`` for the scene's restitution. MuJoCo's
    Euler step resolves that contact in ``pi / (sqrt(k) h)`` steps and starts it on a step,
    not at the touching instant; the error this leaves in the restitution grows with
    ``sqrt(k) h`` (and with ``zeta``), so the export refuses ``sqrt(k) h > 1`` and
    ``b h > 1`` (see the documentation page *MuJoCo* for measured values).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from xml.sax.saxutils import quoteattr

import numpy as np

from hybridoc.errors import ControlsError, HybridocError, SceneError
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ProblemLike, as_ocp, disc_scene

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems import Scene

__all__ = [
    "DEFAULT_STIFFNESS",
    "DEFAULT_SUBSTEPS",
    "IMPEDANCE",
    "MujocoModel",
    "Rollout",
    "contact_damping",
    "import_mujoco",
    "load_model",
    "restitution_of_damping",
    "scene_to_mjcf",
]

DEFAULT_STIFFNESS = 1e6
"""Contact stiffness ``k`` (1/s^2, an acceleration per unit of penetration): a contact lasts
``pi / sqrt(k)``, 3.1 ms at the default, and penetrates ``v / sqrt(k)`` at approach speed
``v`` (2 mm at 2 m/s)."""

DEFAULT_SUBSTEPS = 10
"""MuJoCo steps per control interval ``K``: with the default stiffness and single-collision's
grid (``h = 1 / 4800``), ``sqrt(k) h = 0.21``, about 15 steps per contact."""

IMPEDANCE = 0.9999
"""MuJoCo's constraint impedance ``d`` (``solimp = (d, d, ...)``): constant, at MuJoCo's
largest value. Along a contact's normal the share ``1 - d`` of the other forces (1e-4) goes
through, and ``solref``'s stiffness and damping are the contact's own (MuJoCo divides them
by ``dmax``, here ``d``)."""

_MAX_WH = 1.0  # sqrt(k) h above this: fewer than pi steps per contact
_MAX_BH = 1.0  # b h above this: the explicit damping overshoots within one step


def import_mujoco() -> Any:
    """The ``mujoco`` module, or a :class:`~hybridoc.errors.HybridocError` saying how to
    install it."""
    try:
        import mujoco
    except ImportError as exc:
        raise HybridocError(
            f"MuJoCo is not installed ({exc}); install it with: pip install hybridoc[mujoco]"
        ) from None
    return mujoco


# --------------------------------------------------------------------- restitution


def restitution_of_damping(zeta: float) -> float:
    """Restitution of a linear spring-damper contact that cannot pull, at damping ratio
    ``zeta``.

    The gap ``r`` follows ``r'' + 2 zeta w r' + w^2 r = 0`` from ``r = 0``, ``r' = -v``;
    the contact ends when its force ``-(r'')`` reaches zero, at ``t*`` with
    ``r''(t*) = 0`` (before ``r`` returns to 0 when ``zeta > 0``), and the restitution is
    ``r'(t*) / v``. It depends on ``zeta`` alone; it is 1 at ``zeta = 0``,
    ``exp(-2)`` at ``zeta = 1`` and tends to 0 only as ``zeta`` grows without bound.

    Parameters
    ----------
    zeta
        Damping ratio ``b / (2 sqrt(k))``, >= 0.

    Returns
    -------
    float
        The coefficient of restitution.
    """
    z = float(zeta)
    if not z >= 0.0 or not math.isfinite(z):
        raise SceneError(f"damping ratio must be a finite number >= 0, got {zeta!r}")
    if z < 1.0:
        s = math.sqrt(1.0 - z * z)
        phase = math.atan2(2.0 * z * s, 2.0 * z * z - 1.0)  # w_d t*: r'' = 0
        q = z / s
        return math.exp(-q * phase) * (q * math.sin(phase) - math.cos(phase))
    if z == 1.0:
        return math.exp(-2.0)
    # overdamped: r = A (exp(l1 t) - exp(l2 t)) in units of 1/w, with r'(0) = -1
    s = math.sqrt(z * z - 1.0)
    l1, l2 = -z + s, -z - s
    t = math.log(l2 * l2 / (l1 * l1)) / (l1 - l2)
    return (l2 * math.exp(l2 * t) - l1 * math.exp(l1 * t)) / (l1 - l2)


def contact_damping(restitution: float, stiffness: float = DEFAULT_STIFFNESS) -> float:
    """The damping ``b`` of a contact of stiffness ``k`` with the given restitution.

    Inverts :func:`restitution_of_damping` by bisection on ``zeta`` and returns
    ``b = 2 zeta sqrt(k)``; 0 for ``restitution = 1``.

    Parameters
    ----------
    restitution
        Coefficient of restitution, in ``(0, 1]``.
    stiffness
        ``k`` > 0 (1/s^2).

    Returns
    -------
    float
        ``b`` (1/s), for ``solref = (-k, -b)``.

    Raises
    ------
    SceneError
        ``restitution`` outside ``(0, 1]``: a spring-damper contact always gives back some
        of the approach speed, so 0 cannot be reached.
    """
    e = float(restitution)
    if not 0.0 < e <= 1.0:
        raise SceneError(
            f"restitution = {restitution!r}: MuJoCo's spring-damper contact needs a value in "
            "(0, 1] (a contact that cannot pull always gives back some of the approach "
            "speed; 0 would need infinite damping)"
        )
    k = float(stiffness)
    if not (k > 0.0 and math.isfinite(k)):
        raise SceneError(f"stiffness must be a finite number > 0, got {stiffness!r}")
    if e == 1.0:
        return 0.0
    lo, hi = 0.0, 1.0
    while restitution_of_damping(hi) > e:
        hi *= 2.0
        if hi > 1e12:  # pragma: no cover - e > 0 is reached long before
            raise SceneError(f"restitution = {e!r} is too small to reach by damping")
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if restitution_of_damping(mid) > e:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return 2.0 * 0.5 * (lo + hi) * math.sqrt(k)


# --------------------------------------------------------------------- MJCF


def _num(x: float) -> str:
    """A float that reads back bit for bit (``0`` for zero, without a sign)."""
    x = float(x)
    return "0" if x == 0.0 else repr(x)


def _vec(*xs: float) -> str:
    return " ".join(_num(x) for x in xs)


def _check_settings(scene: Scene, substeps: int, stiffness: float) -> tuple[float, float]:
    """``(h, b)`` for the settings, or a SceneError naming the setting that does not fit."""
    if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
        raise SceneError(f"substeps must be an integer >= 1, got {substeps!r}")
    k = float(stiffness) if isinstance(stiffness, int | float | np.number) else math.nan
    if isinstance(stiffness, bool) or not (k > 0.0 and math.isfinite(k)):
        raise SceneError(f"stiffness must be a finite number > 0, got {stiffness!r}")
    h = scene.horizon / (scene.steps * int(substeps))
    wh = math.sqrt(k) * h
    if scene.n_discs + len(scene.walls) < 2:  # nothing can touch: any step will do
        return h, contact_damping(scene.restitution, k)
    if wh > _MAX_WH:
        need = math.ceil(substeps * wh / _MAX_WH)
        raise SceneError(
            f"stiffness {k:g} with {substeps} substep(s): a contact lasts pi/sqrt(k) = "
            f"{math.pi / math.sqrt(k):.3g} s, only {math.pi / wh:.2g} MuJoCo steps of "
            f"h = {h:.3g} s, and MuJoCo's Euler step makes up energy there (sqrt(k) h = "
            f"{wh:.3g} > {_MAX_WH:g}); use substeps >= {need} or stiffness <= "
            f"{(_MAX_WH / h) ** 2:.3g} (sqrt(k) h <= 0.2, substeps >= "
            f"{math.ceil(substeps * wh / 0.2)}, keeps the velocity error of an elastic "
            "contact under about 1%)"
        )
    b = contact_damping(scene.restitution, k)
    if b * h > _MAX_BH:
        need = math.ceil(substeps * b * h / _MAX_BH)
        raise SceneError(
            f"restitution = {scene.restitution:g} needs the contact damping b = {b:.4g} 1/s, "
            f"more than MuJoCo's explicit step takes at h = {h:.3g} s (b h = {b * h:.3g} > "
            f"{_MAX_BH:g}); use substeps >= {need}"
        )
    return h, b


def _export_scene(problem: Scene | ProblemLike) -> Scene:
    """The scene to export, or a SceneError naming what the export cannot carry."""
    from hybridoc.problems import scene_of

    scene = scene_of(problem, compiled=False)
    if scene is not None:
        return scene
    ocp = as_ocp(problem)
    scene = disc_scene(ocp)
    if ocp.has_bounds:
        raise SceneError(
            f"{ocp.name!r} has control bounds (u_min, u_max): the MJCF export carries the "
            "scene only; export the scene without them"
        )
    if ocp.path is not None:
        raise SceneError(
            f"{ocp.name!r} has path constraints (path), which MJCF cannot express; export "
            "the scene without them"
        )
    return scene


def scene_to_mjcf(
    scene: Scene | ProblemLike,
    *,
    substeps: int = DEFAULT_SUBSTEPS,
    stiffness: float = DEFAULT_STIFFNESS,
) -> str:
    """The MJCF (MuJoCo XML) text of a disc scene.

    ========================  ===================================================
    scene field               MJCF
    ========================  ===================================================
    disc ``name``             body and sphere geom ``name``; joints ``name.x``,
                              ``name.y``
    ``position``              body ``pos`` and the joints' ``ref``: ``qpos`` is the
                              world position
    ``velocity``              ``qvel`` of the keyframe ``initial``
    ``radius``, ``mass``      sphere ``size``, geom ``mass``
    ``actuated``              motors ``name.ux``, ``name.uy`` on the joints (gear 1,
                              no limits), in ``control_labels`` order
    ``target``                a site ``name.target`` (drawn, not simulated)
    wall ``point``,           plane geom at ``pos = point`` with ``zaxis = normal``
    ``normal``, ``name``
    ``horizon``, ``steps``    ``timestep = T / (N K)`` for ``K = substeps``
    ``restitution``           ``solref = (-k, -b)`` with ``b`` from
                              :func:`contact_damping`, ``solimp = (d, d, ...)``
    ``control_weight``,       not in MJCF: :meth:`MujocoModel.cost`
    targets (cost)
    ========================  ===================================================

    Gravity is off, contacts are frictionless (``condim="1"``) and the integrator is
    MuJoCo's (semi-implicit) Euler. A ``[distribution]`` is not exported (the nominal
    scene is).

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`, or anything that names a disc problem
        (:func:`hybridoc.problem.as_ocp`).
    substeps
        ``K``, MuJoCo steps per control interval, >= 1.
    stiffness
        Contact stiffness ``k`` > 0 (1/s^2); see :data:`DEFAULT_STIFFNESS`.

    Returns
    -------
    str
        The MJCF document.

    Raises
    ------
    SceneError
        A problem that is not a disc scene, one with control bounds or path constraints,
        ``restitution = 0``, or settings whose contacts MuJoCo's step cannot resolve
        (``sqrt(k) h > 1`` or ``b h > 1``; the message says which substeps would do).
    """
    scene = _export_scene(scene)
    h, b = _check_settings(scene, substeps, stiffness)
    k = float(stiffness)
    e = scene.restitution
    d = repr(IMPEDANCE)
    lines = [
        f"<mujoco model={quoteattr(scene.name)}>",
        "  <!-- Exported by hybridoc from the disc scene "
        f"{_xml_comment(scene.name)}: T = {_num(scene.horizon)}, N = {scene.steps}, "
        f"{substeps} MuJoCo step(s) per control interval.",
        f"       Contacts: stiffness k = {_num(k)}, damping b = {_num(b)} for restitution "
        f"e = {_num(e)}. The cost ({_num(scene.control_weight)} * integral |u|^2 dt",
        "       + |p(T) - target|^2 of the discs with a target) is not part of MJCF:",
        "       hybridoc.workflows.mujoco.MujocoModel.cost computes it. -->",
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_num(h)}" gravity="0 0 0" integrator="Euler"/>',
        "  <default>",
        f'    <geom condim="1" contype="1" conaffinity="1" margin="0" solref="{_vec(-k, -b)}"',
        f'          solimp="{d} {d} 0.001 0.5 2" rgba="0.5 0.5 0.5 1"/>',
        "  </default>",
        "  <worldbody>",
    ]
    for w in scene.walls:
        lines.append(
            f'    <geom name="{w.name}" type="plane" pos="{_vec(*w.point, 0.0)}" '
            f'zaxis="{_vec(*w.normal, 0.0)}" size="0 0 0.1"/>'
        )
    for disc in scene.discs:
        x, y = disc.position
        colour = "0.85 0.3 0.2 1" if disc.actuated else "0.2 0.4 0.8 1"
        lines += [
            f'    <body name="{disc.name}" pos="{_vec(x, y, 0.0)}">',
            f'      <joint name="{disc.name}.x" type="slide" axis="1 0 0" ref="{_num(x)}"/>',
            f'      <joint name="{disc.name}.y" type="slide" axis="0 1 0" ref="{_num(y)}"/>',
            f'      <geom name="{disc.name}" type="sphere" size="{_num(disc.radius)}" '
            f'mass="{_num(disc.mass)}" rgba="{colour}"/>',
            "    </body>",
        ]
    for disc in scene.discs:
        if disc.target is not None:
            lines.append(
                f'    <site name="{disc.name}.target" pos="{_vec(*disc.target, 0.0)}" '
                'size="0.03" rgba="0.1 0.7 0.2 0.5"/>'
            )
    lines += ["  </worldbody>", "  <actuator>"]
    for label in scene.control_labels():
        name, comp = label.rsplit(".", 1)
        lines.append(f'    <motor name="{label}" joint="{name}.{comp[1]}" gear="1"/>')
    s0 = scene.initial_state()
    n = scene.n_discs
    lines += [
        "  </actuator>",
        "  <keyframe>",
        f'    <key name="initial" qpos="{_vec(*s0[: 2 * n])}" qvel="{_vec(*s0[2 * n :])}"/>',
        "  </keyframe>",
        "</mujoco>",
    ]
    return "\n".join(lines) + "\n"


def _xml_comment(text: str) -> str:
    # '--' may not appear inside an XML comment; scene names may hold it
    return re.sub(r"-{2,}", "-", text)


# --------------------------------------------------------------------- MuJoCo side


@dataclass
class Rollout:
    """A control run in MuJoCo (:meth:`MujocoModel.rollout`).

    Attributes
    ----------
    times
        The ``N K + 1`` step times ``0, h, ..., T``.
    states
        ``(N K + 1, nx)`` states in hybridoc's layout ``[p_1, ..., p_n, v_1, ..., v_n]``.
    controls
        The ``(N K, nu)`` controls applied, one row per MuJoCo step.
    cost, terminal_cost, running_cost
        MuJoCo's cost: ``phi(s(T)) + sum_i L(s_i, u_i) h`` with the problem's ``phi`` and
        ``L``.
    max_penetration
        The deepest contact seen at the start of a step (0 without contacts).
    contact_steps
        The number of steps that began with a contact.
    """

    times: np.ndarray
    states: np.ndarray
    controls: np.ndarray
    cost: float
    terminal_cost: float
    running_cost: float
    max_penetration: float
    contact_steps: int


@dataclass(repr=False)
class MujocoModel:
    """A disc scene as a MuJoCo model, with the maps between MuJoCo's arrays and hybridoc's.

    Made by :func:`load_model`. Joints and motors are found by the names
    :func:`scene_to_mjcf` gives them, so a model edited by hand (other contact parameters,
    another integrator) works as long as those names and the degrees of freedom stay.

    Attributes
    ----------
    problem
        The scene's problem (a :class:`~hybridoc.problems.DiscOCP`; its ``L`` and ``phi``
        are the cost).
    model
        The ``mujoco.MjModel``.
    substeps
        ``K``, MuJoCo steps per control interval (``timestep = T / (N K)``).
    xml
        The MJCF text the model was compiled from.
    """

    problem: HybridOCP
    model: Any
    substeps: int
    xml: str
    _qpos: np.ndarray = field(init=False, repr=False)
    _dof: np.ndarray = field(init=False, repr=False)
    _tangent: np.ndarray = field(init=False, repr=False)
    _act: np.ndarray = field(init=False, repr=False)
    _key: int = field(init=False, repr=False)
    _cost_fns: Any = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        mujoco = import_mujoco()
        m = self.model
        scene = self.scene
        names = [d.name for d in scene.discs]
        joints = [f"{nm}.{c}" for nm in names for c in "xy"]
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in joints]
        missing = [j for j, i in zip(joints, ids, strict=True) if i < 0]
        if missing:
            raise SceneError(f"the MuJoCo model has no joint(s) {', '.join(missing)}")
        labels = list(self.problem.control_labels or [])
        acts = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in labels]
        missing = [a for a, i in zip(labels, acts, strict=True) if i < 0]
        if missing:
            raise SceneError(f"the MuJoCo model has no motor(s) {', '.join(missing)}")
        if m.nv != len(joints) or m.nu != len(labels) or m.na != 0:
            raise SceneError(
                f"the MuJoCo model has {m.nv} degrees of freedom, {m.nu} actuators and "
                f"{m.na} activations; the scene needs {len(joints)}, {len(labels)} and 0"
            )
        dof = np.array([m.jnt_dofadr[i] for i in ids])
        self._qpos = np.array([m.jnt_qposadr[i] for i in ids])
        # mjd_transitionFD's state is [dq (tangent, nv), qvel (nv)]; slide joints: dq = dof
        self._tangent = np.concatenate([dof, m.nv + dof])
        self._dof = dof
        self._act = np.array(acts)
        self._key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "initial")

    @property
    def scene(self) -> Scene:
        """The scene."""
        return disc_scene(self.problem)

    def __repr__(self) -> str:
        return (
            f"MujocoModel({self.problem.name!r}, substeps={self.substeps}, "
            f"timestep={self.timestep!r})"
        )

    @property
    def timestep(self) -> float:
        """MuJoCo's step ``h``."""
        return float(self.model.opt.timestep)

    @property
    def steps(self) -> int:
        """The number of MuJoCo steps over the horizon, ``N K``."""
        return self.problem.steps * self.substeps

    def fine_controls(self, controls: Any) -> np.ndarray:
        """Controls on MuJoCo's steps: ``(N, nu)`` rows held for ``K`` steps each, or
        ``(N K, nu)`` rows as they are.

        Raises
        ------
        ControlsError
            Another shape, or values that are not finite.
        """
        u = as_float_array(getattr(controls, "controls", controls), "controls", error=ControlsError)
        nu, n, k = self.problem.nu, self.problem.steps, self.substeps
        if u.ndim == 1 and nu == 1:
            u = u[:, None]
        if u.ndim != 2 or u.shape[1] != nu or u.shape[0] not in (n, n * k):
            rows = f"{n} or {n * k}" if k > 1 else f"{n}"
            raise ControlsError(
                f"controls: expected {rows} rows (N control intervals, or N*K = {n}*{k} MuJoCo "
                f"steps) and {nu} columns ({', '.join(self.problem.control_labels or [])}), "
                f"got shape {u.shape}"
            )
        if not np.all(np.isfinite(u)):
            raise ControlsError("controls: values must be finite (NaN or inf found)")
        return np.repeat(u, k, axis=0) if u.shape[0] == n and k > 1 else np.array(u)

    def new_data(self) -> Any:
        """A ``mujoco.MjData`` at the scene's initial state (the keyframe ``initial``)."""
        mujoco = import_mujoco()
        data = mujoco.MjData(self.model)
        if self._key >= 0:
            mujoco.mj_resetDataKeyframe(self.model, data, self._key)
        else:  # a model without the keyframe: set the state from the scene
            self.set_state(data, self.problem.x0)
        mujoco.mj_forward(self.model, data)
        return data

    def state(self, data: Any) -> np.ndarray:
        """The state of ``data`` in hybridoc's layout ``[p_1, ..., p_n, v_1, ..., v_n]``."""
        return np.concatenate([data.qpos[self._qpos], data.qvel[self._dof]])

    def set_state(self, data: Any, state: Any) -> None:
        """Put a state in hybridoc's layout into ``data`` (``qpos`` and ``qvel``)."""
        s = np.asarray(state, dtype=float)
        half = s.size // 2
        data.qpos[self._qpos] = s[:half]
        data.qvel[self._dof] = s[half:]

    def _costs(self) -> Any:
        """``L`` and ``phi`` with their gradients, mapped over the steps (CasADi)."""
        if self._cost_fns is None:
            import casadi as ca

            p = self.problem
            s, u = ca.SX.sym("s", p.nx), ca.SX.sym("u", p.nu)
            lv = p.L(s, u)
            run = ca.Function("run", [s, u], [lv, ca.gradient(lv, s), ca.gradient(lv, u)])
            pv = p.phi(s)
            term = ca.Function("term", [s], [pv, ca.gradient(pv, s)])
            self._cost_fns = (run.map(self.steps), term)
        return self._cost_fns

    def _run(self, controls: Any, jacobians: bool, eps: float) -> tuple[Rollout, Any, Any]:
        mujoco = import_mujoco()
        m = self.model
        u = self.fine_controls(controls)
        steps = u.shape[0]
        data = self.new_data()
        # MuJoCo's own arrays per step, put into hybridoc's order once at the end
        qpos = np.empty((steps + 1, m.nq))
        qvel = np.empty((steps + 1, m.nv))
        qpos[0], qvel[0] = data.qpos, data.qvel
        ctrl = np.zeros((steps, m.nu))
        ctrl[:, self._act] = u
        if jacobians:
            a_mj = np.empty((steps, 2 * m.nv, 2 * m.nv))
            b_mj = np.empty((steps, 2 * m.nv, m.nu))
        deepest, touching = 0.0, 0
        for i in range(steps):
            data.ctrl[:] = ctrl[i]
            if jacobians:
                mujoco.mjd_transitionFD(m, data, eps, True, a_mj[i], b_mj[i], None, None)
            mujoco.mj_step(m, data)
            qpos[i + 1], qvel[i + 1] = data.qpos, data.qvel
            if data.ncon:
                touching += 1
                deepest = max(deepest, -float(np.min(data.contact.dist[: data.ncon])))
        states = np.hstack([qpos[:, self._qpos], qvel[:, self._dof]])
        jac = None
        if jacobians:
            rows = self._tangent
            jac = (a_mj[:, rows][:, :, rows], b_mj[:, rows][:, :, self._act])
        h = self.timestep
        run, term = self._costs()
        l_all, dls, dlu = run(states[:-1].T, u.T)
        phi, dphi = term(states[-1])
        running = float(np.sum(np.asarray(l_all))) * h
        terminal = float(phi)
        roll = Rollout(
            times=np.arange(steps + 1) * h,
            states=states,
            controls=u,
            cost=terminal + running,
            terminal_cost=terminal,
            running_cost=running,
            max_penetration=deepest,
            contact_steps=touching,
        )
        grads = None
        if jacobians:
            grads = (np.asarray(dls).T * h, np.asarray(dlu).T * h, np.asarray(dphi).ravel())
        return roll, jac, grads

    def rollout(self, controls: Any) -> Rollout:
        """Run a control in MuJoCo from the scene's initial state.

        Parameters
        ----------
        controls
            ``(N, nu)`` (each row held for ``K`` steps) or ``(N K, nu)`` (one row per MuJoCo
            step), columns in ``control_labels`` order; a Solution is accepted.

        Returns
        -------
        Rollout
        """
        return self._run(controls, False, 0.0)[0]

    def cost(self, controls: Any) -> float:
        """MuJoCo's cost of a control: ``phi(s(T)) + sum_i L(s_i, u_i) h`` (see
        :meth:`rollout`)."""
        return self.rollout(controls).cost

    def cost_and_gradient(self, controls: Any, *, eps: float = 1e-6) -> tuple[float, np.ndarray]:
        """MuJoCo's cost and its gradient, from per-step Jacobians chained backwards.

        At every step ``s_{i+1} = F(s_i, u_i)`` MuJoCo's ``mjd_transitionFD`` gives
        ``A_i = dF/ds`` and ``B_i = dF/du`` by centred finite differences of one step;
        then ``lambda_M = grad phi(s_M)``, ``g_i = h dL/du + B_i^T lambda_{i+1}`` and
        ``lambda_i = h dL/ds + A_i^T lambda_{i+1}``. This is the gradient a user of MuJoCo
        computes; it is not the gradient of the continuous cost (:func:`hybridoc.gradient`).

        Parameters
        ----------
        controls
            As in :meth:`rollout`.
        eps
            Finite-difference step of ``mjd_transitionFD``.

        Returns
        -------
        cost : float
            MuJoCo's cost.
        gradient : numpy.ndarray
            ``dcost/du`` of the shape of ``controls``: for ``(N, nu)`` controls, the sum of
            the gradients of the ``K`` steps each row is held for.
        """
        u_in = as_float_array(
            getattr(controls, "controls", controls), "controls", error=ControlsError
        )
        roll, (a_all, b_all), grads = self._run(controls, True, eps)
        dls, dlu, lam = grads
        g = np.empty_like(roll.controls)
        for i in range(roll.controls.shape[0] - 1, -1, -1):
            g[i] = dlu[i] + b_all[i].T @ lam
            lam = dls[i] + a_all[i].T @ lam
        if u_in.shape[0] == self.problem.steps and self.substeps > 1:
            g = g.reshape(self.problem.steps, self.substeps, -1).sum(axis=1)
        return roll.cost, g.reshape(u_in.shape)


def load_model(
    problem: Scene | ProblemLike,
    *,
    substeps: int = DEFAULT_SUBSTEPS,
    stiffness: float = DEFAULT_STIFFNESS,
    xml: str | Path | None = None,
) -> MujocoModel:
    """A disc scene compiled into MuJoCo.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.problems.Scene` or anything naming a disc problem.
    substeps, stiffness
        As in :func:`scene_to_mjcf`; not used with ``xml``.
    xml
        A ``.xml`` file written by :func:`scene_to_mjcf` (or ``hybridoc export mjcf``),
        perhaps edited, instead of a fresh export; its time step must divide a control
        interval into a whole number of steps.

    Returns
    -------
    MujocoModel

    Raises
    ------
    SceneError
        What :func:`scene_to_mjcf` raises; a file MuJoCo cannot read, or one whose names,
        degrees of freedom or time step do not fit the scene.
    HybridocError
        MuJoCo is not installed.
    """
    mujoco = import_mujoco()
    scene = _export_scene(problem)
    ocp = scene.to_ocp()
    if xml is None:
        text = scene_to_mjcf(scene, substeps=substeps, stiffness=stiffness)
        model = mujoco.MjModel.from_xml_string(text)
        return MujocoModel(problem=ocp, model=model, substeps=int(substeps), xml=text)
    path = Path(xml)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"cannot read MJCF file {str(path)!r}: {exc}") from None
    try:
        model = mujoco.MjModel.from_xml_string(text)
    except ValueError as exc:
        raise SceneError(
            f"MuJoCo cannot read {str(path)!r}: {' '.join(str(exc).split())}"
        ) from None
    ratio = scene.dt / float(model.opt.timestep)
    k = round(ratio)
    if k < 1 or abs(ratio - k) > 1e-9 * ratio:
        raise SceneError(
            f"{str(path)!r}: timestep {model.opt.timestep!r} does not divide the control "
            f"interval T/N = {scene.dt!r} into whole steps"
        )
    return MujocoModel(problem=ocp, model=model, substeps=k, xml=text)
