"""Discrete modes and time dependence, each lowered to one more state coordinate.

Modes
    A system with discrete modes (flight and stance, a valve open or shut), each with its
    own flow ``f_q`` and running cost ``L_q``, is the same model with one more state: the
    last coordinate is the mode index ``q`` (a float: 0, 1, ...), constant along every flow
    and set by the resets. :meth:`HybridOCP.from_modes <hybridoc.ocp.HybridOCP.from_modes>`
    builds it from :class:`Mode` objects and guards with a ``source`` and ``target`` mode:
    ``f = f_q`` and ``L = L_q`` are selected by ``q``, and each guard fires only in its source
    mode. Every method (the judge, the reference, the transcription, gradient descent) then
    solves it unchanged, and the hybrid minimum principle comes out per mode: the
    Hamiltonian is ``L_q + lambda^T f_q`` on each side of a switch, and the costate of ``q``
    decouples (``dH/dq = 0`` between switches).
    The state a user sees is ``(s, q)``, its last label ``"mode"``.

A required final mode
    ``final_mode`` (problems with modes) ties the terminal constraints to a mode: ``s(T)``
    must lie in that mode. The judge reports a control that ends in another mode as an
    infinite terminal violation (:attr:`HybridOCP.terminal_violation
    <hybridoc.ocp.HybridOCP.terminal_violation>`), and the reference searches only mode
    sequences that end there (:meth:`HybridOCP.sequence_admissible
    <hybridoc.ocp.HybridOCP.sequence_admissible>`).

Time-dependent flows and costs
    ``f(t, s, u)`` and ``L(t, s, u)`` (and ``phi``, path and terminal constraints that read
    the time) are the same model with one more state: :meth:`HybridOCP.from_expressions
    <hybridoc.ocp.HybridOCP.from_expressions>` and :meth:`HybridOCP.from_modes
    <hybridoc.ocp.HybridOCP.from_modes>` with ``t=t_sym`` add the time as a state coordinate
    placed after ``s`` (before the mode index, which stays last), with ``t' = 1``,
    ``t(0) = 0``, the label ``"t"``, and every reset keeping it. Every method then solves the
    problem unchanged, and the judge's gradient and the event rule come out exact (the
    costate of ``t`` carries ``dH/dt``: ``lambda_t + H`` is constant under a constant
    control). Guards stay functions of ``s`` (or of ``(s, t)`` where built
    on ``ca.vertcat(s, t)``). With a free final time the cost and constraints see the
    time ``t`` of the stretched grid, since the time coordinate integrates ``t' = 1``.

The functions here build what the two classmethods of :class:`~hybridoc.ocp.HybridOCP`
pass to its constructor (:func:`problem_fields`, :func:`lifted_modes`, :class:`TimeLift`)
and check a problem's modes (:func:`checked_modes`, :func:`mode_index_of`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.arrays import as_float_array
from hybridoc.errors import SceneError
from hybridoc.guards import Guard, casadi_name

__all__ = [
    "MODE_LABEL",
    "Mode",
    "TimeLift",
    "checked_modes",
    "lifted_modes",
    "mode_index_of",
    "problem_fields",
]

MODE_LABEL = "mode"
"""The label of the mode index, the last state coordinate of a problem with modes."""

_SAME_DEPTH = 32
"""How deep :meth:`HybridOCP.from_modes <hybridoc.ocp.HybridOCP.from_modes>` compares the
modes' expressions for equality."""

_MASKED = 1.0
"""The value of a guard outside its source mode: positive (free space, so it neither fires
nor counts as penetrated there) and constant along every flow of those modes (a polynomial
of degree 0, so the guard's declared ``degree`` still holds)."""


@dataclass(frozen=True)
class Mode:
    """A discrete mode of a hybrid system: its flow and its running cost.

    Parameters
    ----------
    name
        Unique name, e.g. ``"stance"``.
    f
        CasADi Function ``(s, u) -> ds/dt`` (``s`` without the mode index).
    L
        Running cost, ``(s, u) -> scalar``; ``None`` for none.
    flow_map
        Optional exact flow map of this mode, ``(s, u, h) -> (s(h), integral_0^h L dt)`` for
        a constant control. When every mode has one, :meth:`HybridOCP.from_modes
        <hybridoc.ocp.HybridOCP.from_modes>` assembles the problem's closed-form flow map from
        them (the judge then needs no integrator).
    """

    name: str
    f: ca.Function
    L: ca.Function | None = None
    flow_map: ca.Function | None = None

    @classmethod
    def from_expressions(
        cls,
        name: str,
        s: ca.SX | ca.MX,
        u: ca.SX | ca.MX,
        f: ca.SX | ca.MX,
        L: ca.SX | ca.MX | float | None = None,
    ) -> Mode:
        """Build a mode from expressions in the state symbol ``s`` and control ``u``."""
        tag = casadi_name(name)
        return cls(
            name=name,
            f=ca.Function(f"f_{tag}", [s, u], [f]),
            L=None if L is None else ca.Function(f"L_{tag}", [s, u], [L]),
        )


def checked_modes(
    modes: Any, guards: Sequence[Guard], final_mode: str | None, x0: np.ndarray
) -> tuple[str, ...] | None:
    """A problem's ``modes`` as a tuple of names (``None`` without modes), checked with its
    guards' source and target modes, its ``final_mode`` and the mode index of ``x0``.

    Raises
    ------
    hybridoc.errors.SceneError
        For names that are not unique non-empty strings, a source, target or final mode
        that is not one of them (or any without modes), or an ``x0`` whose last coordinate
        is not a mode index (:func:`mode_index_of`).
    """
    with_modes = [g.name for g in guards if g.source is not None or g.target is not None]
    if modes is None:
        if final_mode is not None:
            raise SceneError(
                f"final_mode {final_mode!r} needs a problem with modes (build it with "
                "HybridOCP.from_modes)"
            )
        if with_modes:
            raise SceneError(
                f"guard(s) {with_modes} have a source or target mode but the problem has "
                "no modes (build it with HybridOCP.from_modes)"
            )
        return None
    if isinstance(modes, str) or not all(isinstance(m, str) and m for m in modes):
        raise SceneError(f"modes must be a sequence of non-empty names, got {modes!r}")
    modes = tuple(modes)
    if not modes:
        raise SceneError("modes must name at least one mode")
    if len(set(modes)) != len(modes):
        raise SceneError(f"mode names must be unique: {list(modes)}")
    for g in guards:
        for role, m in (("source", g.source), ("target", g.target)):
            if m is not None and m not in modes:
                raise SceneError(
                    f"guard {g.name!r}: unknown {role} mode {m!r}; the modes are {list(modes)}"
                )
    mode_index_of(modes, x0, what="x0")
    if final_mode is not None and final_mode not in modes:
        raise SceneError(f"final_mode {final_mode!r} is not one of the modes {list(modes)}")
    return modes


def mode_index_of(
    modes: tuple[str, ...] | None, state: Any, *, what: str = "state", problem: str = "ocp"
) -> int:
    """The mode index of a state (its last coordinate) among ``modes``; the body of
    :meth:`HybridOCP.mode_index <hybridoc.ocp.HybridOCP.mode_index>`.

    Raises
    ------
    hybridoc.errors.SceneError
        Without modes (naming the ``problem``), or for an index that is not an integer or
        out of range.
    """
    if modes is None:
        raise SceneError(f"{problem}: the problem has no modes")
    arr = np.asarray(state, dtype=float).ravel()
    q = float(arr[-1]) if arr.size else math.nan
    if not (math.isfinite(q) and q == round(q) and 0 <= q < len(modes)):
        raise SceneError(
            f"{what}: the mode index (the last state coordinate) must be an integer from 0 "
            f"to {len(modes) - 1} (modes {list(modes)}), got {q!r}"
        )
    return int(q)


def _as_modes(modes: Any, s: Any, u: Any) -> list[Mode]:
    """``from_modes``'s modes as :class:`Mode` objects."""
    if isinstance(modes, Mapping):
        out = []
        for name, spec in modes.items():
            if not isinstance(spec, tuple | list) or len(spec) != 2:
                raise SceneError(f"mode {name!r}: expected (f, L) expressions, got {spec!r}")
            f, L = spec
            out.append(Mode.from_expressions(str(name), s, u, f, None if L is None else L))
        modes = out
    modes = list(modes)
    if not modes:
        raise SceneError("from_modes needs at least one mode")
    for m in modes:
        if not isinstance(m, Mode):
            raise SceneError(f"modes must be Mode objects or a dict name -> (f, L), got {m!r}")
    return modes


def _in_state(expr: Any, s: Any, u: Any, xs: Any, uu: Any) -> Any:
    """An expression in ``(s, u)`` rewritten in the augmented state's ``s`` part."""
    return ca.Function("tmp", [s, u], [expr])(xs, uu)


def _in_s(expr: Any, s: Any, xs: Any) -> Any:
    """An expression in ``s`` rewritten in the augmented state's ``s`` part."""
    return ca.Function("tmp", [s], [expr])(xs)


class TimeLift:
    """The lowering of time dependence: expressions in ``(s, t, u)`` rewritten in the state
    ``x = (s, t)`` (module notes, "Time-dependent flows and costs")."""

    def __init__(self, s: Any, t: Any, u: Any) -> None:
        sym = ca.SX if isinstance(s, ca.SX) else ca.MX
        if not isinstance(t, ca.SX | ca.MX) or not t.is_symbolic() or t.numel() != 1:
            raise SceneError(f"t must be one scalar CasADi symbol (ca.SX.sym('t')), got {t!r}")
        self.s, self.t, self.u = s, t, u
        self.ns = int(s.numel())
        self.x = sym.sym("st", self.ns + 1)
        self.xs, self.xt = self.x[: self.ns], self.x[self.ns]

    def _call(self, args: list[Any], values: list[Any], expr: Any, what: str) -> Any:
        if not isinstance(expr, ca.SX | ca.MX):  # a number, e.g. L = 0
            expr = type(self.x)(as_float_array(expr, what))
        try:
            fn = ca.Function(f"lift_{casadi_name(what)}", args, [expr])
        except RuntimeError as exc:
            names = ", ".join(a.name() if a.is_symbolic() else "?" for a in args)
            raise SceneError(
                f"{what} must be an expression in ({names}) only: {str(exc).splitlines()[0]}"
            ) from None
        return fn(*values)

    def of_stu(self, expr: Any, what: str) -> Any:
        """``expr(s, t, u)`` as an expression in ``(x, u)``."""
        return self._call([self.s, self.t, self.u], [self.xs, self.xt, self.u], expr, what)

    def of_st(self, expr: Any, what: str) -> Any:
        """``expr(s, t)`` as an expression in ``x``."""
        return self._call([self.s, self.t], [self.xs, self.xt], expr, what)

    def x0(self, x0: Any) -> np.ndarray:
        arr = as_float_array(x0, "x0").ravel()
        if arr.size != self.ns:
            raise SceneError(
                f"x0 must give the {self.ns} components of s (the time, 0 at the start, is "
                f"added), got {arr.size}"
            )
        return np.r_[arr, 0.0]

    def labels(self, kwargs: dict[str, Any]) -> dict[str, Any]:
        """``kwargs`` with ``"t"`` appended to the state labels."""
        out = dict(kwargs)
        given = out.get("state_labels")
        if given is None:
            given = [f"s{i}" for i in range(self.ns)]
        given = [*map(str, given)]
        if len(given) != self.ns:
            raise SceneError(f"state_labels must name the {self.ns} components of s")
        out["state_labels"] = [*given, "t"]
        return out

    def _of_state(self, fn: ca.Function | None, what: str) -> Any:
        """A function of ``s`` or of ``(s, t)`` at the symbolic ``x``."""
        if fn is None:
            return None
        n = fn.size1_in(0) if fn.n_in() == 1 else -1
        if n == self.ns:
            return fn(self.xs)
        if n == self.ns + 1:
            return fn(self.x)
        raise SceneError(f"{what} must be a Function of s ({self.ns}) or of (s, t) ({self.ns + 1})")

    def _of_state_u(self, fn: ca.Function, what: str) -> Any:
        """A reset ``(s, u)`` or ``((s, t), u)`` at the symbolic ``(x, u)``."""
        n, nu = fn.size1_in(0), int(self.u.numel())
        if fn.size1_in(1) != nu:
            raise SceneError(f"{what} must be a Function (s, u) -> s with u of size {nu}")
        if n == self.ns:
            return fn(self.xs, self.u)
        if n == self.ns + 1:
            return fn(self.x, self.u)
        raise SceneError(
            f"{what} must be a Function of (s, u) ({self.ns}) or of ((s, t), u) ({self.ns + 1})"
        )

    def guard(self, g: Guard) -> Guard:
        """A guard of ``s`` (or ``(s, t)``) as a guard of ``x``; its reset keeps the time."""
        if not isinstance(g, Guard):
            raise SceneError(f"guards must be Guard objects, got {g!r}")
        tag = casadi_name(g.name)
        if g.uses_control:
            reset = self._of_state_u(g.reset, f"guard {g.name!r}: the reset")
        else:
            reset = self._of_state(g.reset, f"guard {g.name!r}: the reset")
        if reset.numel() == self.ns + 1:
            reset = reset[: self.ns]
        if reset.numel() != self.ns:
            raise SceneError(f"guard {g.name!r}: the reset must return the {self.ns} components")
        det = self._of_state(g.detector, f"guard {g.name!r}: the detector")
        lifted = ca.vertcat(reset, self.xt)
        return dataclasses.replace(
            g,
            psi=ca.Function(f"psi_{tag}", [self.x], [self._of_state(g.psi, f"guard {g.name!r}")]),
            reset=ca.Function(f"g_{tag}", [self.x, self.u], [lifted])
            if g.uses_control
            else ca.Function(f"g_{tag}", [self.x], [lifted]),
            detector=None if det is None else ca.Function(f"det_{tag}", [self.x], [det]),
        )

    def mode(self, name: str, spec: Any) -> Mode:
        """A mode of ``from_modes`` (``(f, L)`` expressions in ``(s, t, u)``, or a
        :class:`Mode` of ``s``) as a mode of ``x``; a Mode's flow map advances the time."""
        x, u = self.x, self.u
        if isinstance(spec, Mode):
            L = None if spec.L is None else ca.Function(f"L_{name}", [x, u], [spec.L(self.xs, u)])
            fm = None
            if spec.flow_map is not None:
                h = type(self.x).sym("h")
                end, cost = spec.flow_map(self.xs, u, h)
                fm = ca.Function(
                    f"fm_{casadi_name(name)}", [x, u, h], [ca.vertcat(end, self.xt + h), cost]
                )
            return Mode(
                spec.name,
                f=ca.Function(
                    f"f_{casadi_name(name)}", [x, u], [ca.vertcat(spec.f(self.xs, u), 1.0)]
                ),
                L=L,
                flow_map=fm,
            )
        if not isinstance(spec, tuple | list) or len(spec) != 2:
            raise SceneError(f"mode {name!r}: expected (f, L) expressions, got {spec!r}")
        f, L = spec
        return Mode.from_expressions(
            name,
            x,
            u,
            ca.vertcat(self.of_stu(f, f"mode {name!r}: f"), 1.0),
            None if L is None else self.of_stu(L, f"mode {name!r}: L"),
        )


def _transition(
    g: Guard, x: Any, u: Any, ns: int, index: dict[str, float], names: list[str]
) -> Guard:
    """A transition of ``from_modes`` as a guard of the augmented state ``x = (s, q)``."""
    if not isinstance(g, Guard):
        raise SceneError(f"transitions must be Guard objects, got {g!r}")
    for role, m in (("source", g.source), ("target", g.target)):
        if m is None:
            raise SceneError(f"transition {g.name!r} needs a {role} mode (one of {names})")
        if m not in index:
            raise SceneError(f"transition {g.name!r}: unknown {role} mode {m!r}; modes {names}")
    for what, fn in (("psi", g.psi), ("detector", g.detector)):
        if fn is not None and (fn.n_in() != 1 or fn.size1_in(0) != ns):
            raise SceneError(f"transition {g.name!r}: {what} must be a Function of s ({ns})")
    g.check_reset(ns, int(u.numel()), what=f"transition {g.name!r}")
    xs, q = x[:ns], x[ns]
    here = ca.fabs(q - index[g.source]) < 0.5  # type: ignore[index]
    tag = casadi_name(g.name)

    def masked(fn: ca.Function, prefix: str) -> ca.Function:
        return ca.Function(f"{prefix}_{tag}", [x], [ca.if_else(here, fn(xs), _MASKED)])

    after = ca.vertcat(g.reset_at(xs, u), index[g.target])  # type: ignore[index]
    return dataclasses.replace(
        g,
        psi=masked(g.psi, "psi"),
        reset=ca.Function(f"g_{tag}", [x, u] if g.uses_control else [x], [after]),
        detector=None if g.detector is None else masked(g.detector, "det"),
    )


def lifted_modes(lift: TimeLift, modes: Any, s: Any, u: Any) -> list[Mode]:
    """``from_modes``'s modes (a dict of expressions in ``(s, t, u)`` or :class:`Mode`
    objects of ``s``) as modes of the time-lifted state ``x = (s, t)``."""
    return (
        [lift.mode(str(n), spec) for n, spec in modes.items()]
        if isinstance(modes, Mapping)
        else [lift.mode(m.name, m) for m in _as_modes(modes, s, u)]
    )


def _mode_objects(modes: Any, s: Any, u: Any, initial_mode: str) -> tuple[list[Mode], list[str]]:
    """``from_modes``'s modes as :class:`Mode` objects and their names, checked: unique
    names, the initial mode among them."""
    mode_list = _as_modes(modes, s, u)
    names = [m.name for m in mode_list]
    if len(set(names)) != len(names):
        raise SceneError(f"mode names must be unique: {names}")
    if initial_mode not in names:
        raise SceneError(f"initial_mode {initial_mode!r} is not one of the modes {names}")
    return mode_list, names


def _checked_sizes(mode_list: list[Mode], x0: Any, ns: int, nu: int) -> np.ndarray:
    """``x0`` (of ``s``) as a float array, checked with every mode's flow against the sizes
    ``ns`` of ``s`` and ``nu`` of ``u``."""
    x0_s = as_float_array(x0, "x0").ravel()
    if x0_s.size != ns:
        raise SceneError(
            f"x0 must give the {ns} components of s (the mode index is added from "
            f"initial_mode), got {x0_s.size}"
        )
    for m in mode_list:
        if m.f.n_in() != 2 or m.f.size1_in(0) != ns or m.f.size1_in(1) != nu:
            raise SceneError(f"mode {m.name!r}: f must be a Function (s, u) -> ds/dt")
        if m.f.size_out(0) != (ns, 1):
            raise SceneError(f"mode {m.name!r}: f must return {ns} derivatives")
    return x0_s


def _select(values: list[Any], q: Any) -> Any:
    """The value of the current mode ``q`` among one expression per mode."""
    # component by component: one that is the same expression in every mode (y' = v
    # in flight and stance, a common running cost) stays free of the mode, so that
    # structural checks (a control weight independent of the state) still see it
    rows = []
    for i in range(values[0].numel()):
        col = [v[i] for v in values]
        if all(ca.is_equal(c, col[0], _SAME_DEPTH) for c in col[1:]):
            rows.append(col[0])
            continue
        # mode k where q < k + 1/2: robust to a q that an NLP moves by rounding
        out = col[-1]
        for k in range(len(col) - 2, -1, -1):
            out = ca.if_else(q < k + 0.5, col[k], out)
        rows.append(out)
    return ca.vertcat(*rows)


def _flow_map(
    mode_list: list[Mode], x: Any, uu: Any, xs: Any, q: Any, sym: Any
) -> ca.Function | None:
    """The flow map of ``x = (s, q)`` (``xs`` and ``q`` its parts) from the modes' own,
    ``None`` unless every mode has one."""
    if not all(m.flow_map is not None for m in mode_list):
        return None
    h = sym.sym("h")
    ends = [m.flow_map(xs, uu, h) for m in mode_list]  # type: ignore[misc]
    return ca.Function(
        "flow_map",
        [x, uu, h],
        [ca.vertcat(_select([e[0] for e in ends], q), q), _select([e[1] for e in ends], q)],
        ["s", "u", "h"],
        ["s_end", "cost"],
    )


def _labels(state_labels: Sequence[str] | None, ns: int) -> list[str]:
    """The labels of ``(s, q)``: those given for ``s`` (or ``s0``, ``s1``, ...) and
    :data:`MODE_LABEL`."""
    if state_labels is not None:
        labels = [*map(str, state_labels), MODE_LABEL]
        if len(labels) != ns + 1:
            raise SceneError(f"state_labels must name the {ns} components of s")
    else:
        labels = [f"s{i}" for i in range(ns)] + [MODE_LABEL]
    return labels


def problem_fields(
    s: ca.SX | ca.MX,
    u: ca.SX | ca.MX,
    *,
    modes: Sequence[Mode] | Mapping[str, tuple[Any, Any]],
    transitions: Sequence[Guard],
    initial_mode: str,
    phi: ca.SX | ca.MX,
    x0: Sequence[float] | np.ndarray,
    path: ca.SX | ca.MX | None,
    state_labels: Sequence[str] | None,
    terminal_eq: ca.SX | ca.MX | None,
    terminal_ineq: ca.SX | ca.MX | None,
) -> dict[str, Any]:
    """The fields of the problem :meth:`HybridOCP.from_modes
    <hybridoc.ocp.HybridOCP.from_modes>` builds (without the time: :func:`lifted_modes`
    and :class:`TimeLift` lower it first), on the state ``x = (s, q)``.

    The arguments are those of ``from_modes``.

    Returns
    -------
    dict
        ``f``, ``L``, ``phi``, ``guards``, ``x0``, ``flow_map``, ``path``,
        ``state_labels``, ``modes``, ``terminal_eq`` and ``terminal_ineq``, for the
        constructor of :class:`~hybridoc.ocp.HybridOCP`.

    Raises
    ------
    hybridoc.errors.SceneError
        For modes or transitions that do not fit ``s``, ``u`` or each other, or an ``x0``
        or ``state_labels`` that does not fit ``s``.
    """
    mode_list, names = _mode_objects(modes, s, u, initial_mode)
    ns, nu = s.numel(), u.numel()
    x0_s = _checked_sizes(mode_list, x0, ns, nu)
    sym = ca.SX if isinstance(s, ca.SX) else ca.MX
    x, uu = sym.sym("x", ns + 1), sym.sym("u", nu)
    xs, q = x[:ns], x[ns]
    index = {name: float(k) for k, name in enumerate(names)}
    f_sel = _select([m.f(xs, uu) for m in mode_list], q)
    L_sel = _select([sym(0.0) if m.L is None else m.L(xs, uu) for m in mode_list], q)
    phi_fn = ca.Function("phi_s", [s], [phi])
    guards = [_transition(g, x, uu, ns, index, names) for g in transitions]
    fm = _flow_map(mode_list, x, uu, xs, q, sym)
    labels = _labels(state_labels, ns)
    return {
        "f": ca.Function("f", [x, uu], [ca.vertcat(f_sel, 0)]),
        "L": ca.Function("L", [x, uu], [L_sel]),
        "phi": ca.Function("phi", [x], [phi_fn(xs)]),
        "guards": guards,
        "x0": np.r_[x0_s, index[initial_mode]],
        "flow_map": fm,
        "path": None
        if path is None
        else ca.Function("path", [x, uu], [_in_state(path, s, u, xs, uu)]),
        "state_labels": labels,
        "modes": tuple(names),
        "terminal_eq": None
        if terminal_eq is None
        else ca.Function("terminal_eq", [x], [_in_s(terminal_eq, s, xs)]),
        "terminal_ineq": None
        if terminal_ineq is None
        else ca.Function("terminal_ineq", [x], [_in_s(terminal_ineq, s, xs)]),
    }
